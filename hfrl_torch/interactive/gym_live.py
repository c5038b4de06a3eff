"""``train.py domain=gym agent=dqn trainer=interactive``: a person teaches a DQN on any Gymnasium task from
the browser, watching the task's own frames (``render_mode="rgb_array"``).

The learner (``experiment/learners/gym_dqn.py``) plays B boards of one batched env; the person watches board
0. Three pieces join the page to the learner's TorchRL env:

* :class:`FrameKeeper` wraps board 0's Gymnasium env and renders it right after each step, before the
  vector env's same-step autoreset starts the next episode, so that the frame of an episode's last step
  shows how it ended. It renders only when the page will show the frame.
* :class:`GymWatcher`, a TorchRL transform of the learner's env, paces each env step to the page's speed
  while the person teaches, shows the frame (a PNG) and records in the session's timeline what it shows:
  the step, its action and the simulated time of that action. With the page open but the person away it
  shows a frame about five times a second and does not pace; with the page closed it renders nothing.
* :class:`BrowserGymTrainer`, the trainer the learner's ``HumanFeedback`` transform asks at every step,
  takes the presses off the session's queue, credits each on the simulated clock and logs it.

**Time.** The simulated clock runs ``domain.seconds_per_step`` per step (the clock H^ credits on and the
simulated oracle judges on); the page's speed is in steps per wall second, by default one over it, so the
two clocks keep pace. A press at wall time w is filed under the frame on screen at ``w - r`` (r: the
session's reaction allowance, 0.3 s), which shows the result of the action taken at ``t_k`` on the simulated
clock, and credited at ``min(t_k + r, now)``: where the simulated oracle's judgement of that action would
be (it judges r after the action), so H^ credits a press as it credits the oracle's feedback.
"""

from __future__ import annotations

import base64
import io
from collections.abc import Callable
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from PIL import Image
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.fusion.fusion import changed_by_teaching
from hfrl_torch.interactive.live import BrowserQueueTrainer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.interactive.timeline import credit_time

__all__ = ["BrowserGymTrainer", "FrameKeeper", "GymWatcher", "png_data_url"]

UNPACED_FRAME_S = 0.2  # wall seconds between frames while the page is open and the person away
PROGRESS_S = 1.0  # wall seconds over which the pace of the time left is measured
MAX_SIDE = 640  # frames larger than this on a side are scaled down to it (aspect kept)
# zlib level: CartPole's 600 x 400 frame in 28 ms and 5 kB on this 2-core machine at load average 9 (level
# 6: 58 ms and 2.3 kB; level 1 no faster than 3)
PNG_LEVEL = 3


def png_data_url(frame: np.ndarray, max_side: int = MAX_SIDE) -> str:
    """``frame`` ([H, W, 3] uint8) as a ``data:image/png;base64,...`` URL for the page, scaled down to at
    most ``max_side`` pixels on its longer side."""
    image = Image.fromarray(np.ascontiguousarray(frame), "RGB")
    if max(image.size) > max_side:
        image.thumbnail((max_side, max_side), Image.Resampling.BILINEAR)
    out = io.BytesIO()
    image.save(out, format="PNG", compress_level=PNG_LEVEL)
    return "data:image/png;base64," + base64.b64encode(out.getvalue()).decode("ascii")


class FrameKeeper(gym.Wrapper):
    """Board 0's env (made with ``render_mode="rgb_array"``), rendered right after each step while
    ``wanted()`` says the page will show it; :meth:`take` hands the frame over once."""

    def __init__(self, env: gym.Env, wanted: Callable[[], bool]) -> None:
        super().__init__(env)
        self.wanted = wanted
        self._frame: np.ndarray | None = None

    def step(self, action: Any) -> tuple[Any, Any, bool, bool, dict[str, Any]]:
        out = self.env.step(action)
        self._frame = self.env.render() if self.wanted() else None
        return out

    def take(self) -> np.ndarray | None:
        """The frame rendered after the last step (None: none was wanted, or it was taken already)."""
        frame, self._frame = self._frame, None
        return frame


class BrowserGymTrainer(BrowserQueueTrainer):
    """A person in the browser as the trainer of board 0 (the ``Trainer`` the ``HumanFeedback`` transform
    asks at every step).

    Each step it drains the page's queue and files each press under the frame the session says it was made
    on (``session.filed``: the frame on screen ``reaction_s`` before it), credited at ``min(t_k + r, now)``
    (the module docstring): ``t_k`` the simulated time of the action that frame shows, ``now`` the step's.

    :param session: the page's session; its queue holds the presses (``human:browser``, wall clock).
    :param log: the feedback log every press goes to (session ``<run>/browser``, numbered as the journal).
    """

    discrete = False  # credited on the continuous simulated clock, as the oracle's events are

    def label(self, event: FeedbackEvent) -> FeedbackEvent:
        """``event`` filed under the frame it was made on, at its credit time (the step before its time, as
        ``QueueTrainer``, where no frame was shown)."""
        seen, _ = self.session.filed(event)
        if seen is None:
            return super().label(event).stamped(self.press_session)
        return FeedbackEvent(
            time=credit_time(seen, None, self.session.reaction_s, self._now),
            value=event.value,
            source=event.source,
            step=seen.step,
            episode=seen.episode,
            session=self.press_session,
        )


class GymWatcher(Transform):
    """Shows board 0 on the page after every env step, paced while a person teaches (module docstring).

    Put it in the env's ``Compose`` after ``StepCounter`` and ``RewardSum`` and before the trainer's
    ``HumanFeedback`` (it reads the step's ``keys.CLOCK``, the simulated time of the action), and play the
    env that :meth:`watch` returns as board 0.

    :param session: the page's session (speed, pause, presence, frames, timeline, progress).
    :param seconds_per_step: the simulated clock's time per step (``domain.seconds_per_step``).
    :param total_steps: the run's budget in steps of one board (``agent.frames`` / boards), for the page.
    :param weight: the current weight on H^, for the page (None: not shown).
    :param frame_s: wall seconds between frames while nobody teaches.
    """

    def __init__(
        self,
        session: TeachingSession,
        seconds_per_step: float,
        total_steps: int,
        weight: Callable[[], float] | None = None,
        frame_s: float = UNPACED_FRAME_S,
    ) -> None:
        if not seconds_per_step > 0:
            raise ValueError(f"GymWatcher seconds_per_step must be > 0, got {seconds_per_step!r}")
        super().__init__()
        self.session, self.seconds_per_step = session, float(seconds_per_step)
        self.total_steps, self.weight, self.frame_s = int(total_steps), weight, float(frame_s)
        self.keeper: FrameKeeper | None = None
        self.episode = 0  # board 0's episodes ended so far
        self.frames = 0
        self.steps = self.taught = 0  # steps since the last point of the curve, and those a person taught
        self._last_frame = -float("inf")
        self._progress_at: tuple[float, float] | None = None  # (wall, steps done) where the pace was measured
        self._rate: float | None = None  # steps per wall second over the last second or more
        self.without_you: int | None = (
            None  # the last step's action by Q alone, where the teaching changed it
        )
        self.steered = [0, 0]  # board 0's steps of this episode the teaching changed, and all of them
        session.set_live(False)  # nothing to judge before the first frame

    def watch(self, env: gym.Env) -> FrameKeeper:
        """``env`` (board 0, ``render_mode="rgb_array"``) wrapped to render the frames this watcher shows."""
        self.keeper = FrameKeeper(env, self.wants_frame)
        return self.keeper

    def wants_frame(self) -> bool:
        """Whether the step being taken will be shown: a page is open, and the person teaches or the last
        frame is ``frame_s`` old."""
        s = self.session
        return s.clients > 0 and (s.here or s.clock() - self._last_frame >= self.frame_s)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset

    def _steer(self, tensordict: TensorDictBase) -> None:
        """Count board 0's step, and whether the teaching changed its action: Q alone (``keys.ENV_VALUES``)
        rates another higher, and the fused values chose the one taken (a policy without them: unknown)."""
        self.steered[1] += 1
        self.without_you = None
        env, fused = tensordict.get(keys.ENV_VALUES, None), tensordict.get(keys.FUSED_VALUES, None)
        if env is None or fused is None:
            return
        n = env.shape[-1]
        env, fused = env.reshape(-1, n)[:1], fused.reshape(-1, n)[:1]
        mask = tensordict.get(keys.ACTION_MASK, None)
        mask = torch.ones_like(env, dtype=torch.bool) if mask is None else mask.reshape(-1, n)[:1]
        action = tensordict.get(keys.ACTION).reshape(-1)[:1]
        best = int(changed_by_teaching(env, action, mask, fused))
        if best >= 0:
            self.steered[0] += 1
            self.without_you = best

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        self.steps += 1
        self._steer(tensordict)
        ended = bool(next_tensordict.get(keys.DONE).reshape(-1)[0])
        frame = None if self.keeper is None else self.keeper.take()
        if self.session.page_open():
            teaching = self.session.teaching()
            if teaching:
                self.taught += 1
                self.session.wait_turn()
            if frame is not None and (teaching or self.session.clock() - self._last_frame >= self.frame_s):
                self._show(frame, tensordict, next_tensordict, ended, teaching)
        if ended:
            self.episode += 1
            self.steered = [0, 0]
        return next_tensordict

    def _show(
        self,
        frame: np.ndarray,
        tensordict: TensorDictBase,
        next_tensordict: TensorDictBase,
        ended: bool,
        teaching: bool,
    ) -> None:
        """Publish board 0's ``frame`` after the step of ``tensordict``; record what a press on it judges."""
        action = int(tensordict.get(keys.ACTION).reshape(-1)[0])
        step = int(tensordict.get(keys.STEP_COUNT).reshape(-1)[0])  # of this action in its episode, 0-based
        sim = float(tensordict.get(keys.CLOCK).reshape(-1)[0])  # when the action was taken
        returned = float(next_tensordict.get(keys.EPISODE_REWARD).reshape(-1)[0])
        self.session.publish(
            {
                "type": "gym",
                "phase": "watch" if teaching else "away",
                "image": png_data_url(frame),
                "episode": self.episode + 1,
                "step": step + 1,
                "action": f"action {action}",
                "return": round(returned, 4),
                "ended": ended,
                "weight": None if self.weight is None else float(self.weight()),
                "without_you": None if self.without_you is None else f"action {self.without_you}",
                "steered": list(self.steered),
            }
        )
        label = f"action {action} at step {step + 1} of episode {self.episode + 1}"
        self._last_frame = self.session.shown(sim, self.episode, step, label)
        if self.frames == 0:
            self.session.set_live(True)
        self.frames += 1
        self._progress(sim / self.seconds_per_step + 1)

    def _progress(self, done: float) -> None:
        """Tell the page the steps of board 0 done and left with each frame (never behind the frame), and
        how long those left take at the pace measured over the last second or more."""
        wall = self.session.clock()
        if self._progress_at is None:
            self._progress_at = (wall, done)
        elif wall - self._progress_at[0] >= PROGRESS_S:
            self._rate = (done - self._progress_at[1]) / (wall - self._progress_at[0])
            self._progress_at = (wall, done)
        left = max(self.total_steps - round(done), 0)
        self.session.set_progress(
            unit="steps",
            done=min(round(done), self.total_steps),
            total=self.total_steps,
            left=left,
            left_s=left / self._rate if self._rate else None,
        )

    def taught_share(self) -> float:
        """The share of the steps since the last call that a person taught (0 with none); starts anew."""
        share = self.taught / self.steps if self.steps else 0.0
        self.steps = self.taught = 0
        return share

    def get_extra_state(self) -> dict[str, Any]:
        """Board 0's episodes so far (the presses' episode numbers go on across a resume)."""
        return {"episode": self.episode}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        """Continue :meth:`get_extra_state`'s count."""
        try:
            self.episode = int(state["episode"])
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"bad browser page state in the checkpoint ({e!r})") from None
