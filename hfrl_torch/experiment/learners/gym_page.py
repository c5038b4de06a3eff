"""The browser page of every ``domain=gym`` learner (``trainer=interactive``): DQN, PPO and TAMER alone.

A person watches board 0, made with ``render_mode="rgb_array"`` and shown after every step by
:class:`~hfrl_torch.interactive.gym_live.GymWatcher`, which paces the learner's env to the page's speed
(``domain.seconds_per_step`` a step by default, so the page and the simulated clock keep pace); the presses
come off the page's queue through :class:`~hfrl_torch.interactive.gym_live.BrowserGymTrainer`, credited on
the same simulated clock and logged (and journaled) as every domain's are. The learner keeps its own loop:
this mixin builds the page's parts and says what the page shows of the run.
"""

from __future__ import annotations

from collections.abc import Callable
from functools import cached_property
from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from torchrl.envs import EnvBase, RewardSum, StepCounter
from torchrl.envs.transforms import Transform

from hfrl_torch.envs.gym_task import GymTask, make_gym_batch
from hfrl_torch.experiment.factories import FeedbackWiring, make_feedback_wiring
from hfrl_torch.experiment.run import Point
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.interactive.gym_live import BrowserGymTrainer, GymWatcher
from hfrl_torch.interactive.live import LiveTeaching
from hfrl_torch.interactive.messages import MAX_SPEED, MIN_SPEED

__all__ = ["SCORE_KEY", "GymPage"]

SCORE_KEY = "eval/greedy_return"  # the points of every domain=gym learner


class GymPage:
    """What a ``domain=gym`` learner needs for a person's page. The learner sets ``teaching`` from
    :meth:`page_wiring`'s result before it makes its env with :meth:`page_env` and :meth:`page_transforms`,
    calls :meth:`show_points` with each chunk's points and keeps :meth:`page_state` in its checkpoint."""

    cfg: DictConfig
    task: GymTask
    boards: int
    frames_total: int
    fusion: Fusion
    teaching: LiveTeaching | None

    @property
    def seconds_per_step(self) -> float:
        """The simulated clock's time per env step (``domain.seconds_per_step``), which H^ credits on."""
        return float(self.cfg.domain.seconds_per_step)

    @property
    def watched_boards(self) -> int:
        """The boards a trainer watches (its effort): a person board 0, a simulated trainer every board."""
        return 1 if self.teaching is not None else self.boards

    def page_weight(self) -> Callable[[], float] | None:
        """What gives the weight on H^ the page shows with each frame (None: none, TAMER acting on H^
        alone)."""
        return lambda: float(self.fusion.weight()[0])

    @cached_property
    def watcher(self) -> GymWatcher | None:
        """What shows board 0 on a person's page and paces it (None: nobody teaches in the browser)."""
        if self.teaching is None:
            return None
        steps = -(-self.frames_total // self.boards)
        return GymWatcher(self.teaching.session, self.seconds_per_step, steps, self.page_weight())

    def page_wiring(
        self, run_dir: Path, simulated: Callable[[FeedbackLog], Any], boards: int | None = None
    ) -> FeedbackWiring:
        """The feedback wiring (``make_feedback_wiring``: ``simulated``'s trainer, or the page for
        ``trainer=interactive``, starting at one step per ``domain.seconds_per_step`` within the page's
        speeds and naming the task and its curve's axes; ``boards``: a channel of that many boards)."""
        e = self.cfg.agent.eval_episodes
        info = {
            "task": self.task.label,
            "curve_x": f"env steps, all {self.boards} copies of the task",
            "curve_y": "greedy return per episode",
            "curve_note": f"Return of the greedy policy, mean of {e} test episodes",
        }
        return make_feedback_wiring(
            self.cfg,
            run_dir,
            self.fusion,
            simulated,
            lambda session, log: BrowserGymTrainer(session, log),
            view="gym",
            boards=boards,
            fsync_simulated=False,
            speed=min(max(1.0 / self.seconds_per_step, MIN_SPEED), MAX_SPEED),
            info=info,
        )

    def page_env(self, boards: int, seed: int) -> EnvBase:
        """``boards`` seeded copies of the task, board 0 the watched one when a person teaches."""
        first = None if self.watcher is None else self.watcher.watch(self.task.make_watched())
        return make_gym_batch(self.task, boards, seed, first=first)

    def page_transforms(self) -> list[Transform]:
        """Each episode's step count and return, then the watcher (it reads both)."""
        return [StepCounter(), RewardSum(), *filter(None, [self.watcher])]

    def announce_page(self) -> None:
        """Print the page's URL and wait for it (``trainer.wait_for_page_s``); a resumed run waits too:
        nobody teaches it until the page opens."""
        if self.teaching is not None:
            self.teaching.announce(float(self.cfg.trainer.wait_for_page_s), "learning from the task alone")

    def show_points(self, points: list[Point]) -> None:
        """The page's curve: each point with the share of its steps a person taught."""
        if self.watcher is None or self.teaching is None:
            return
        share = self.watcher.taught_share()
        for p in points:
            self.teaching.session.add_point(p.step, p.record[f"{SCORE_KEY}_mean"], share)

    def page_state(self) -> dict[str, Any]:
        """What the checkpoint keeps of the page (empty without one)."""
        return {} if self.watcher is None else {"page": self.watcher.get_extra_state()}

    def load_page_state(self, state: dict[str, Any]) -> None:
        """Continue :meth:`page_state`'s count (a run saved before the page kept any: from 0)."""
        if self.watcher is not None:
            self.watcher.set_extra_state(state.get("page", {"episode": 0}))
