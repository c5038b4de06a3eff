"""TAMER alone on any Gymnasium task (or a TorchRL env of the user's): ``train.py domain=gym agent=tamer
trainer=oracle trainer.reference=<module:callable or a gym run>``.

H^ is Deep TAMER's network on the observation (``human=mlp``, the H^ that ``agent=dqn`` fuses), and the
learner acts greedily on it (the fusion component's ``human_only`` rule): it learns only from its trainer's
feedback, never from the environment's reward. The trainer is the simulated oracle against
``trainer.reference``, the value proxy, a replayed log, or a person in the browser watching board 0
(``trainer=interactive``, ``gym_page``). One learner plays ``agent.boards`` copies of the task, a
simulated trainer judging each (a person: board 0), on a simulated clock of ``domain.seconds_per_step`` per
step. At every step, as in Tetris's TAMER (``tetris_games.py``): the feedback due on the clock comes out of
the channel and H^ learns from it (credited over the recent decisions, with Deep TAMER's feedback replay),
the learner chooses, the trainer judges the choice (its events go into the channel) and H^ remembers it. Once
the trainer leaves (``trainer.leave_after`` episodes of the learner, all boards together, or simulated
minutes), H^ is frozen (no delivery, credit or replay; the events still waiting are dropped) and keeps
acting. The points are the greedy policy's mean return on ``agent.eval_episodes`` fresh episodes, the same
seeds at every point, as ``agent=dqn``'s.

A checkpoint is written at every point (about 0.5 MB), and a resumed run equals the uninterrupted one: the
checkpoint keeps H^ (its buffer included), the trainer, the channel and every action played, and the resumed
run replays those actions on the freshly seeded task to stand where the run stood (CartPole-v1 on 8 boards
replays about 3,000 frames per CPU second; 900 per wall second on this shared 2-core machine). A task that
does not replay the same (e.g. a callable ignoring its seed) restarts its episodes instead, and the report
says so. A run a person taught keeps no actions and restarts its episodes on a new seed (nothing a person did
can be replayed); the presses logged after its checkpoint are learned once.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.envs import Compose, EnvBase, TransformedEnv

from hfrl_torch import keys
from hfrl_torch.agents.dqn import HumanValuesModule
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.common.logger import Logger
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.stats import summarize
from hfrl_torch.experiment.checks import check_gym_tamer
from hfrl_torch.experiment.factories import (
    make_deep_tamer,
    make_fusion,
    make_gym_trainer,
)
from hfrl_torch.experiment.learners.gym_dqn import (
    GymTaskParts,
    greedy_returns,
    observation,
    observation_net,
)
from hfrl_torch.experiment.learners.gym_page import SCORE_KEY, GymPage
from hfrl_torch.experiment.learners.tetris_games import TRAINER_LABELS
from hfrl_torch.experiment.run import FramesLearner, Point
from hfrl_torch.fusion.transform import FusionModule
from hfrl_torch.interactive.live import taught_by_person

__all__ = ["GymTamer"]

DECISION_KEYS = (keys.HUMAN_VALUES, keys.FUSED_VALUES, keys.FUSION_WEIGHT)  # the policy's, not the env's


class GymTamer(GymTaskParts, GymPage, FramesLearner):
    """Deep TAMER alone on ``agent.boards`` copies of a task, taught by its trainer (module docstring)."""

    domain = "gym"
    agent = "tamer"

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_gym_tamer(cfg)

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        super().__init__(cfg, run_dir, checkpoint)
        a = cfg.agent
        self.seed = int(cfg.seed)
        torch.manual_seed(component_seed(self.seed, "agent"))  # H^'s initialisation
        self.boards, self.frames_total = int(a.boards), int(a.frames)
        self.eval_every, self.eval_episodes = int(a.eval_every), int(a.eval_episodes)
        model = observation_net(self.spaces, list(cfg.human.cells), self.scale)
        self.human = make_deep_tamer(cfg, model, observation, self.boards)
        self.fusion = make_fusion(cfg, type(self), 1, option="human_only")
        self.policy = TensorDictSequential(
            HumanValuesModule(self.human, [keys.OBSERVATION]), FusionModule(self.fusion, "greedy")
        )
        wiring = self.page_wiring(
            run_dir, lambda log: make_gym_trainer(cfg, self.spaces.actions, log), boards=self.boards
        )
        self.log, self.trainer, self.teaching = wiring.log, wiring.trainer, wiring.teaching
        self.channel, self.departure = wiring.channel, wiring.departure
        self.steps = 0  # steps of every board (frames = boards x steps)
        self.points = 0
        self.games = torch.zeros(self.boards, dtype=torch.int64)  # each board's finished episodes
        self.events = 0  # feedback events H^ learned from
        self.positive = 0
        self.trainer_seconds = 0.0
        self.left_at: int | None = None  # the frame at which the trainer left
        self.finished: list[float] = []  # returns of the training episodes ended since the last point
        self.played: list[torch.Tensor] = []  # every step's actions [B] since the task was seeded
        self.restarts = 0  # resumes whose episodes restarted (a person's run, or a task that did not replay)
        if checkpoint is not None:
            self._load(checkpoint["state"])
        else:
            self.env, self.td = self._seeded_env()

    def _seeded_env(self) -> tuple[EnvBase, TensorDictBase]:
        """The training boards, seeded afresh (a new seed after each restart), board 0 shown on a person's
        page, and their first observation."""
        seed = component_seed(self.seed, "env", self.restarts)
        parts = Compose(*self.page_transforms())
        env = TransformedEnv(self.page_env(self.boards, seed), parts, auto_unwrap=True)
        return env, env.reset()

    def page_weight(self) -> Callable[[], float] | None:
        return None  # TAMER acts on H^ alone: no weight to show

    # ---------------------------------------------------------------- the loop

    @property
    def frames(self) -> int:
        return self.steps * self.boards

    @property
    def episodes(self) -> int:
        return int(self.games.sum())

    @property
    def description(self) -> str:
        return "TAMER gym"

    @property
    def clock(self) -> float:
        """The simulated time of the next step's action (seconds)."""
        return self.steps * self.seconds_per_step

    @property
    def present(self) -> bool:
        """Whether the trainer still watches (``trainer.leave_after``): the learner's episodes over all its
        boards, or its simulated minutes."""
        return self.departure.present_one(self.episodes, self.clock)

    @property
    def who(self) -> str:
        """Who gives the feedback, for the run's TensorBoard text."""
        t = self.cfg.trainer
        if self.teaching is not None:
            return taught_by_person("board 0")
        label = TRAINER_LABELS.get(t.name, t.name)
        judged = f" against trainer.reference={t.reference}" if t.name != "replay" else f" of {t.log}"
        return f"{label} (a simulated or replayed trainer, not a person){judged}, one per board"

    def start(self, logger: Logger) -> None:
        if self.restarts and self.resumed and self.teaching is None:
            logger.text("resume", "the task did not replay the same actions the same way: episodes restarted")
        if not self.resumed:
            logger.text("trainer", f"{self.who}; {self.departure.describe()}; human={self.cfg.human.name}")
        self.announce_page()

    def advance(self) -> list[Point]:
        if self.points == 0 and self.frames == 0:
            points = [self._point()]  # the untrained policy: where every curve starts
        else:
            goal = min(self.frames_total, self.points * self.eval_every)
            while self.frames < goal and not self.ending:
                self._step()
            # ended early (Finish and save, Ctrl-C): the checkpoint keeps the steps, a resumed run goes on
            points = [self._point()] if self.frames >= goal else []
        self.show_points(points)
        return points

    def _step(self) -> None:
        """One step of every board: H^ learns from what is due, acts greedily, and is judged."""
        now, present = self.clock, self.present
        if present:
            delivery = self.channel.deliver(now)
            given = delivery.get(keys.FEEDBACK_MASK)
            if bool(given.any()):
                self.events += int(self.human.learn(delivery).sum())
                self.positive += int((given & (delivery.get(keys.FEEDBACK) > 0)).sum())
        elif self.left_at is None:
            self.left_at = self.frames
        td = self.policy(self.td)
        action = td.get(keys.ACTION)
        if present:
            self.channel.put_events(self.trainer.give(td, action, now, self.games))
            self.human.record(td, action, now)
            self.trainer_seconds += self.watched_boards * self.seconds_per_step
        if self.teaching is None:  # a person's run is not replayed
            self.played.append(action.reshape(-1).to(torch.int32))
        td = td.exclude(*DECISION_KEYS)
        if self.watcher is not None:  # the page files a press by when the action it shows was taken
            td.set(keys.CLOCK, torch.full((self.boards,), now, dtype=torch.float64))
        td, self.td = self.env.step_and_maybe_reset(td)
        self.steps += 1
        nxt = td.get("next")
        done = nxt.get(keys.DONE).reshape(-1)
        if bool(done.any()):
            returns = nxt.get(keys.EPISODE_REWARD).reshape(-1)
            self.finished += returns[done].tolist()
            if present:
                self.trainer.end_games(done, returns)
            self.games += done.to(torch.int64)

    def _point(self) -> Point:
        done = summarize(torch.tensor(self.finished, dtype=torch.float64)) if self.finished else {}
        record: dict[str, Any] = {
            "frames": self.frames,
            **greedy_returns(self.task, self.eval_episodes, self.seed, self.policy, self.fusion),
            "train/episodes": self.episodes,
            "train/return": done.get("mean", math.nan),
            "feedback_events": float(self.events),
            "feedback/positive_share": self.positive / self.events if self.events else 0.0,
            "trainer_minutes": self.trainer_seconds / 60.0,
            "trainer/present": float(self.present),
            "human/updates": self.human.updates,
        }
        self.finished = []
        self.points += 1
        return Point(record, self.frames)

    # ------------------------------------------------------------- checkpoints

    def checkpoint(self) -> dict[str, Any]:
        state = {
            "steps": self.steps,
            "points": self.points,
            "games": self.games.clone(),
            "events": [self.events, self.positive],
            "trainer_seconds": self.trainer_seconds,
            "left_at": self.left_at,
            "finished": list(self.finished),
            "played": torch.stack(self.played)
            if self.played
            else torch.zeros(0, self.boards, dtype=torch.int32),
            "observation": self.td.get(keys.OBSERVATION).clone(),
            "restarts": self.restarts,
            "human": self.human.state_dict(),
            "fusion": self.fusion.state_dict(),
            "trainer": self.trainer.state_dict(),
            "channel": self.channel.state_dict(),
            "log_seq": self.log.last_seq,
            "rng": torch.get_rng_state(),
            **self.page_state(),
        }
        return {"state": state, "policy": self.policy_payload()}

    def _load(self, state: dict[str, Any]) -> None:
        self.steps, self.points = int(state["steps"]), int(state["points"])
        self.games = state["games"].clone()
        self.events, self.positive = (int(v) for v in state["events"])
        self.trainer_seconds = float(state["trainer_seconds"])
        self.left_at = None if state["left_at"] is None else int(state["left_at"])
        self.finished = [float(v) for v in state["finished"]]
        self.restarts = int(state["restarts"])
        self.human.load_state_dict(state["human"])
        self.fusion.load_state_dict(state["fusion"])
        self.trainer.load_state_dict(state["trainer"])
        self.channel.load_state_dict(state["channel"])
        person = self.teaching is not None
        # simulated: the events after the checkpoint come again, once; a person's presses logged after it (or
        # recovered from the journal) are learned now
        self.channel.put_board(0, self.log.resume(state["log_seq"], regenerated=not person))
        torch.set_rng_state(state["rng"])
        if person:  # nothing a person did replays: the episodes restart on a new seed
            self.restarts += 1
            (self.env, self.td), self.played = self._seeded_env(), []
            self.load_page_state(state)
        else:
            self.env, self.td = self._seeded_env()
            self._replay(state["played"], state["observation"])

    def _replay(self, played: torch.Tensor, observed: torch.Tensor) -> None:
        """Stand where the saved run stood: its actions again on the freshly seeded task; if the task does not
        end where it did, its episodes restart on a new seed (counted in ``restarts``)."""
        td = self.td
        for action in played:
            _, td = self.env.step_and_maybe_reset(td.set(keys.ACTION, action.to(torch.int64)))
        if torch.equal(td.get(keys.OBSERVATION), observed):
            self.td, self.played = td, list(played)
            return
        self.restarts += 1
        self.env.close()
        (self.env, self.td), self.played = self._seeded_env(), []

    def policy_payload(self) -> dict[str, Any]:
        """What ``evaluate.py`` plays: H^ greedily, on the task it learned."""
        return export_policy(
            "gym_tamer",
            task=OmegaConf.to_container(self.cfg.domain, resolve=True),
            observation_size=self.spaces.observation_size,
            observation_shape=list(self.spaces.observation_shape),
            actions=self.spaces.actions,
            scale=list(self.scale),
            cells=list(self.cfg.human.cells),
            model=self.human.model.state_dict(),
        )

    # ------------------------------------------------------------------ results

    def report(self, final: dict[str, Any]) -> list[str]:
        low, high = final.get(f"{SCORE_KEY}_ci95_low"), final.get(f"{SCORE_KEY}_ci95_high")
        lines = [
            f"Done: {final['frames']} frames; greedy policy {final[f'{SCORE_KEY}_mean']:.2f} return per "
            f"episode (95% CI {low:.2f}..{high:.2f} over {self.eval_episodes} fresh episodes)"
        ]
        curve = [r for r in self.history if self.x_key in r]
        if len(curve) > 1:
            shown = ", ".join(f"{r[f'{SCORE_KEY}_mean']:.1f}" for r in curve)
            lines.append(f"Curve (greedy return every {self.eval_every} frames): {shown}")
        left = "" if self.left_at is None else f"; the trainer left at frame {self.left_at}, H^ frozen since"
        lines.append(
            f"Feedback:         {self.events} events of the "
            f"{TRAINER_LABELS.get(self.cfg.trainer.name, self.cfg.trainer.name)}{left}"
        )
        if self.restarts and self.teaching is None:
            lines.append(
                f"Resumed {self.restarts}x on a task that did not replay the same: episodes restarted"
            )
        lines.append(f"Feedback log:     {self.log.path}")
        return lines

    def score(self, final: dict[str, Any]) -> float | None:
        return final.get(f"{SCORE_KEY}_mean")

    def hparam_metrics(self, final: dict[str, Any]) -> dict[str, float]:
        return {f"hparam/{SCORE_KEY.split('/')[-1]}": final[f"{SCORE_KEY}_mean"]}

    def close(self) -> None:
        self.env.close()
        self.end_teaching("agent.frames", 2 * self.frames_total)
        self.log.close()
