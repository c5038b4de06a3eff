"""``train.py domain=keepaway trainer=interactive``: a person teaches Sarsa keepers from the browser.

One person watches one field: the run has one learner (``agent.learners=1``, the default with
``trainer=interactive``), and the page shows field 0. Three pieces join the live page to the keepers' loop
(``experiment/learners/keepaway_sarsa.py``):

* :class:`KeepawayWatcher` shows every 100 ms simulator cycle of the field on the page, paced to the page's
  speed while the person teaches, and adds the hold times to the page's learning curve. It hooks the
  simulator's ``step`` (one call per cycle) because an env step runs many cycles, and a pass shown only
  at its start and end would be impossible to judge.
* the session's ``ScreenTimeline`` (``timeline.py``) remembers when each frame was shown (wall clock),
  which simulated moment it showed and what a press on it judges.
* :class:`BrowserKeeperTrainer`, the keepers' trainer, turns the presses into events on the field's
  simulated clock, where H^ credits them.

**Time.** H^ credits feedback on the field's simulated clock (seconds, 10 cycles each), while a press is
stamped with the wall clock. A press at wall time w is credited at ``min(S(w - r) + r, now)``, where
S(w') is the simulated time of the frame on screen at w', r = 0.3 s the reaction allowance of both domains
(``timeline.REACTION_S``, near the mode of the gamma(2.0, 0.28) credit density) and ``now`` the field's
clock when the event is read. At real time this is S(w), what was on screen at the press. At other
speeds, or after a pause, the credit still centres on what the person saw about r seconds before
pressing: the person's reaction delay is not stretched or squeezed by the speed.

**Speed.** The page's speed is in decision periods per wall second: one period is
``domain.decision_period_cycles`` cycles (5 when a trainer watches: the thesis's 500 ms). So 2 is real
time (10 cycles a second), which is the default, 0.5 a quarter of it and 20 ten times faster.

**Nobody watching.** With the page closed, or "I'm away", the loop runs at full speed from the
environment alone (the H^ learned so far still counts in the fusion), and an open page gets a frame about
five times a second, covered by a notice of how much simulated time is left and about how long that takes
at the current pace. Opening the page, or "I'm here", brings back the pacing and the teaching.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torch import Tensor

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.envs.keepaway.params import KeepawayConfig
from hfrl_torch.envs.keepaway.records import KeepawayRecords
from hfrl_torch.envs.keepaway.simulator import KeepawaySimulator, KeepawayState
from hfrl_torch.feedback.events import FeedbackEvent, FeedbackQueue
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.interactive.journal import browser_session
from hfrl_torch.interactive.session import SOURCE, TeachingSession
from hfrl_torch.interactive.timeline import ScreenTimeline, credit_time

if TYPE_CHECKING:
    from hfrl_torch.interactive.live import LiveTeaching

CYCLES_PER_SECOND = 10
UNPACED_FRAME_S = 0.2  # wall seconds between frames while nobody teaches
RECENT_EPISODES = 10  # episodes in the page's mean hold time
PROGRESS_S = 1.0  # wall seconds between the page's updates of what is left
ORDINALS = ("nearest", "second-nearest", "third-nearest", "fourth-nearest", "fifth-nearest")


def move_words(action: int) -> str:
    """What a keeper's macro-action would have done, as the page says it (0 holds the ball, k >= 1 passes
    to the k-th nearest teammate)."""
    if action == 0:
        return "would have held the ball"
    nearest = ORDINALS[action - 1] if action <= len(ORDINALS) else f"{action}th-nearest"
    return f"would have passed to its {nearest} teammate"


class BrowserKeeperTrainer:
    """A person in the browser, as the keepers' trainer (the ``KeeperTrainer`` protocol) of one field.

    ``give`` returns no events: a person does not judge on a schedule. ``poll`` drains the page's queue,
    places each press on the field's simulated clock (see the module's docstring), logs it with that time
    and returns one event per call; the others wait for the next calls (the loop takes one event
    per call, and a press credited in the past is due at once whenever the channel delivers it).

    :param session: the page's session; its queue holds the presses (``human:browser``, stamped with the
        wall clock).
    :param fields: B, the fields of the run (the person watches ``field``; the others get nothing).
    :param log: the feedback log every event goes to, with its simulated time and the run's session.
    :param field: the watched field.

    What the page showed when is the session's timeline (the watcher writes it), and r its
    ``reaction_s``: the filing the page is told in a press's acknowledgement is the one credited here.
    """

    source = SOURCE
    discrete = False  # a press is credited on the field's continuous clock (``credit_time``)

    def __init__(
        self,
        session: TeachingSession,
        fields: int = 1,
        log: FeedbackLog | None = None,
        field: int = 0,
    ) -> None:
        if not 0 <= field < fields:
            raise ValueError(f"BrowserKeeperTrainer field={field} is not one of the run's {fields} fields")
        self.session = session
        self.queue: FeedbackQueue = session.queue
        self.fields, self.field = fields, field
        self.log = log
        self.press_session = "" if log is None else browser_session(log.session)
        self.timeline: ScreenTimeline = session.timeline
        self.waiting: deque[FeedbackEvent] = deque()
        self.given = 0
        self.positive = 0
        self._now = 0.0  # the watched field's clock at the last poll
        session.log_left = self.log_left

    def new_episodes(self, starting: Tensor) -> None:
        """Nothing to draw: the person comes and goes through the page."""

    def give(
        self, obs: Tensor, action: Tensor, deciding: Tensor, time: Tensor, keeper: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """No events at decisions (values and times [B] of zeros): presses come through ``poll``."""
        b = action.shape[0]
        return torch.zeros(b, dtype=torch.float64), torch.zeros(b, dtype=torch.float64)

    def credit_time(self, event: FeedbackEvent, now: float) -> tuple[float, int, int]:
        """The simulated time a press is credited at, given the field's clock ``now``, and the episode and
        decision of the frame it is filed under (``session.filed``; -1 when nothing was shown yet)."""
        seen, _ = self.session.filed(event)
        if seen is None:
            return now, -1, -1
        return credit_time(seen, None, self.session.reaction_s, now), seen.episode, seen.step

    def _credited(self, pressed: list[FeedbackEvent], now: float) -> list[FeedbackEvent]:
        """The presses placed on the field's clock (``now``: its time), logged."""
        credited = []
        for ev in pressed:
            t, episode, step = self.credit_time(ev, now)
            credited.append(
                FeedbackEvent(
                    time=t,
                    value=ev.value,
                    source=ev.source,
                    step=step,
                    episode=episode,
                    session=self.press_session,
                )
            )
        return credited if self.log is None else self.log.extend(credited)

    def log_left(self, pressed: list[FeedbackEvent]) -> None:
        """Log the presses left in the queue when the run stops (``TeachingSession.log_left``), on the
        field's clock of the last poll; nobody learns from them in this run."""
        self._credited(pressed, self._now)

    def poll(self, clock: Tensor) -> tuple[Tensor, Tensor]:
        """The next press on the watched field: values [B] float64 (0: none) and simulated times [B]."""
        pressed = self.queue.drain()
        self._now = float(clock[self.field])
        if pressed:
            credited = self._credited(pressed, self._now)
            self.waiting.extend(credited)
            self.given += len(credited)
            self.positive += sum(ev.value > 0 for ev in credited)
        values = torch.zeros(self.fields, dtype=torch.float64)
        times = torch.zeros(self.fields, dtype=torch.float64)
        if self.waiting:
            ev = self.waiting.popleft()
            values[self.field], times[self.field] = ev.value, ev.time
        return values, times

    def state_dict(self) -> dict[str, Any]:
        """The counts, and the presses logged but not yet handed to the run (a resumed run gives them)."""
        return {
            "given": self.given,
            "positive": self.positive,
            "waiting": [ev.to_dict() for ev in self.waiting],
            "now": self._now,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue the counts and the waiting presses of a saved run (older checkpoints kept no presses)."""
        try:
            self.given, self.positive = int(state["given"]), int(state["positive"])
            self.waiting = deque(FeedbackEvent(**ev) for ev in state.get("waiting", []))
            self._now = float(state.get("now", 0.0))
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"bad browser-trainer state in the checkpoint ({e!r})") from None


def _round(xy: list[float]) -> list[float]:
    return [round(xy[0], 2), round(xy[1], 2)]


class KeepawayWatcher:
    """Shows the watched field on the page, paces the loop while a person teaches, draws the curve.

    Call :meth:`attach` with the env's simulator (frames and pacing, every cycle) and call the watcher with
    every env step's tensordict (episode ends).

    :param trainer: the browser trainer; the watcher uses its session (speed, pause, presence, frames,
        curve, timeline).
    :param records: the run's records (the field's clock, episode and decisions).
    :param config: the task (region, decision period).
    :param weight: the watched learner's current weight on H^, for the page (None: not shown).
    :param curve_every: episodes per point of the page's learning curve (mean hold time).
    :param frame_s: wall seconds between frames while nobody teaches.
    :param budget_s: the run's budget in simulated seconds per learner (None: a budget of episodes).
    :param budget_episodes: the run's budget in episodes (0: none).
    """

    def __init__(
        self,
        trainer: BrowserKeeperTrainer,
        records: KeepawayRecords,
        config: KeepawayConfig,
        weight: Callable[[], float] | None = None,
        curve_every: int = 10,
        frame_s: float = UNPACED_FRAME_S,
        budget_s: float | None = None,
        budget_episodes: int = 0,
    ) -> None:
        if curve_every < 1:
            raise ValueError(f"KeepawayWatcher curve_every must be >= 1, got {curve_every!r}")
        self.session, self.trainer, self.records = trainer.session, trainer, records
        self.config, self.weight = config, weight
        self.field = trainer.field
        self.curve_every, self.frame_s = curve_every, frame_s
        self.budget_s, self.budget_episodes = budget_s, int(budget_episodes)
        self.cycle_share = 1.0 / config.decision_period_cycles  # of one paced "action"
        self.recent: deque[float] = deque(maxlen=RECENT_EPISODES)
        self.block: list[float] = []
        self.block_cycles = self.block_taught = 0  # cycles of the curve's block so far, and those taught
        self.action = "-"
        self.target = -1
        self.frames = 0
        self._last_frame = -math.inf
        self._progress_at: tuple[float, float] | None = None  # (wall, simulated s) of the last update
        self._decided: tuple[int, int] | None = None  # (episode, decision) of the last decision shown
        self._alone: int | None = None  # the coming decision's move by Q alone, where the teaching changed it
        self.without_you: str | None = (
            None  # "keeper 2 would have held the ball", where the teaching changed it
        )
        self.steered = [0, 0]  # decisions of the field's episode the teaching changed, and all of them
        self.session.set_live(False)  # nothing to judge before the first frame

    @property
    def real_time_speed(self) -> float:
        """The page's speed that plays at real time (decision periods per second)."""
        return CYCLES_PER_SECOND / self.config.decision_period_cycles

    def attach(self, sim: KeepawaySimulator) -> None:
        """Wrap ``sim.step`` so that every cycle ends in :meth:`cycle`."""
        step = sim.step

        def step_and_show(*args: Any, **kwargs: Any) -> Any:
            with torch.inference_mode():  # the same ops and bits, without autograd dispatch: ~25 % less CPU
                out = step(*args, **kwargs)
            self.cycle(sim.state)
            return out

        sim.step = step_and_show  # type: ignore[method-assign]

    def deciding(self, alone: int) -> None:
        """The field's keeper decides in the coming step; ``alone``: the move Q alone would make where the
        teaching changed it (:func:`~hfrl_torch.fusion.fusion.changed_by_teaching`), else -1."""
        self._alone = alone if alone >= 0 else None

    def cycle(self, state: KeepawayState) -> None:
        """After a simulator cycle: wait for its turn while a person teaches, then show it."""
        self.block_cycles += 1
        f = self.field
        cycles = int(state.episode_cycles[f])
        holder = int(state.prev_holder[f])
        # the last decision is followed with the page closed too, so that a page opened mid-episode names it
        if holder >= 0 and int(state.last_decision[f, holder]) == cycles - 1:  # decided this cycle
            self.target = int(state.pass_target[f])
            self.action = (
                f"keeper {holder + 1} holds the ball"
                if self.target < 0
                else f"keeper {holder + 1} passes to keeper {self.target + 1}"
            )
            self.steered[1] += 1
            self.steered[0] += self._alone is not None
            self.without_you = (
                None if self._alone is None else f"keeper {holder + 1} {move_words(self._alone)}"
            )
            self._alone = None
        if not self.session.page_open():
            return
        teaching = self.session.teaching()
        if teaching:
            self.block_taught += 1
            self.session.wait_turn(self.cycle_share)
        else:
            wall = self.session.clock()
            if wall - self._last_frame < self.frame_s:
                return
        sim = (int(self.records.finished_cycles[f]) + cycles) / CYCLES_PER_SECOND
        episode = int(self.records.episodes[f])
        step = int(self.records.decisions[f].sum()) - 1
        frame = self.frame(state, teaching)
        self.session.publish(frame)
        if step >= 0:
            self._decided = (episode, step)
            label = f"{self.action} (episode {episode + 1}, {frame['time_s']:.1f} s)"
        elif self._decided is not None:  # before an episode's first decision: the credit goes to the last
            episode, step = self._decided  # decisions of the episode before
            label = f"the end of episode {episode + 1}"
        else:
            label = ""  # nothing decided yet: nothing to judge
        self._last_frame = self.session.shown(sim, episode, step, label)
        if self.frames == 0:
            self.session.set_live(True)
        self.frames += 1
        self._progress()

    def _progress(self) -> None:
        """Tell the page what is left of the run, about once a second: simulated time (or episodes) and
        the wall time that takes at the pace of the last second."""
        wall, f = self.session.clock(), self.field
        sim = int(self.records.learner_clock[f]) / CYCLES_PER_SECOND
        if self._progress_at is not None and wall - self._progress_at[0] < PROGRESS_S:
            return
        rate = None
        if self._progress_at is not None and wall > self._progress_at[0]:
            rate = (sim - self._progress_at[1]) / (wall - self._progress_at[0])
        self._progress_at = (wall, sim)
        if self.budget_s:
            left = max(self.budget_s - sim, 0.0)
            left_s = left / rate if rate else None
            self.session.set_progress(
                unit="simulated s", done=sim, total=self.budget_s, left=left, left_s=left_s
            )
        elif self.budget_episodes:
            done = int(self.records.episodes[f])
            self.session.set_progress(
                unit="episodes",
                done=done,
                total=self.budget_episodes,
                left=max(self.budget_episodes - done, 0),
            )

    def frame(self, state: KeepawayState, teaching: bool = True) -> dict[str, Any]:
        """What the page draws of the watched field now (JSON-able)."""
        f, n, c = self.field, self.config.keepers, self.config
        pos = state.pos[f].tolist()
        ball, keepers, takers = pos[0], pos[1 : 1 + n], pos[1 + n :]
        dist = [math.dist(k, ball) for k in keepers]
        nearest = min(range(n), key=dist.__getitem__)
        holder = nearest if dist[nearest] <= c.physics.kickable_distance else -1
        return {
            "type": "keepaway",
            "phase": "watch" if teaching else "away",
            "region": [c.length, c.width],
            "keepers": [_round(p) for p in keepers],
            "takers": [_round(p) for p in takers],
            "ball": _round(ball),
            "holder": holder,
            "target": self.target if holder < 0 else -1,
            "action": self.action,
            "episode": int(self.records.episodes[f]) + 1,
            "time_s": int(state.episode_cycles[f]) / CYCLES_PER_SECOND,
            "mean_hold_s": sum(self.recent) / len(self.recent) if self.recent else None,
            "weight": None if self.weight is None else float(self.weight()),
            "real_time": self.real_time_speed,
            "without_you": self.without_you,
            "steered": list(self.steered) if self.steered[1] else None,
        }

    def __call__(self, td: TensorDictBase) -> None:
        """After an env step: the hold time of an episode that ended, and a point of the curve every
        ``curve_every`` episodes (marked with the share of its cycles the person taught)."""
        after = td["next"]
        f = self.field
        if not bool(after[keys.DONE].reshape(-1)[f]):
            return
        self.action, self.target = "-", -1
        self.without_you, self.steered = None, [0, 0]
        seconds = int(after[keys.EPISODE_CYCLES].reshape(-1)[f]) / CYCLES_PER_SECOND
        self.recent.append(seconds)
        self.block.append(seconds)
        if len(self.block) >= self.curve_every:
            taught = self.block_taught / self.block_cycles if self.block_cycles else 0.0
            self.session.add_point(
                int(self.records.episodes[f]) + 1, sum(self.block) / len(self.block), taught
            )
            self.block.clear()
            self.block_cycles = self.block_taught = 0


def wait_for_teacher(cfg: DictConfig, teaching: LiveTeaching) -> None:
    """Print the page's URL to stderr and wait up to ``trainer.wait_for_page_s`` for it to open."""
    teaching.announce(float(cfg.trainer.wait_for_page_s), "the keepers learn on their own")
