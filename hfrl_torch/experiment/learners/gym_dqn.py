"""DQN on any Gymnasium task (or a TorchRL env of the user's), alone or with a trainer's H^ fused:
``train.py domain=gym domain.env_id=<id> agent=dqn [fusion=<scheme> trainer.reference=<module:callable>]``.

Q is one MLP from the observation vector to one value per action (inputs scaled by one over the observation
space's bound where it is finite). H^ is Deep TAMER's network on the same observation (``human=mlp``), taught
by the simulated oracle against the user's reference policy (``trainers.reference_oracle``), its events
credited over the simulated clock (``domain.seconds_per_step`` per step). TorchRL's ``StepCounter`` numbers
each episode's steps (the events' ``step``) and ``RewardSum`` keeps its return, before any reward-level
fusion: each ended episode's return ends the fusion's episode (the trust factor, the bandit). The points are
the greedy policy's mean return on ``agent.eval_episodes`` fresh episodes, the same seeds at every point.

With ``trainer=interactive`` a person teaches from the browser instead (``interactive/gym_live.py``): board 0
is made with ``render_mode="rgb_array"`` and shown on the page after every step, paced to the page's speed
(``domain.seconds_per_step`` a step by default), and the presses are credited on the same simulated clock.
"""

from __future__ import annotations

from functools import cached_property
from pathlib import Path
from typing import Any, ClassVar

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs import EnvBase, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.transforms import Compose, Transform

from hfrl_torch import keys
from hfrl_torch.agents.dqn import DeepQ, HumanValues
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.common.logger import Logger
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.gym_task import GymTask, TaskSpaces, make_gym_batch
from hfrl_torch.experiment.checks import check_gym_dqn, gym_spaces
from hfrl_torch.experiment.factories import (
    FeedbackWiring,
    make_deep_tamer,
    make_dqn,
    make_gym_task,
    make_gym_trainer,
)
from hfrl_torch.experiment.learners.deep_q import DeepQLearner
from hfrl_torch.experiment.learners.gym_page import SCORE_KEY, GymPage
from hfrl_torch.experiment.run import Point
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.models.cnn import ActionCNN
from hfrl_torch.models.mlp import ActionMLP
from hfrl_torch.trainers import Trainer
from hfrl_torch.trainers.departure import Departure
from hfrl_torch.trainers.transform import HumanFeedback

__all__ = [
    "GymDQN",
    "GymTaskParts",
    "greedy_returns",
    "gym_env",
    "input_scale",
    "observation",
    "observation_net",
    "play_returns",
]


def input_scale(spaces: TaskSpaces) -> list[float]:
    """One over each observation's bound where the space bounds it (MountainCar's velocity is within 0.07),
    else 1; ``[1.0]`` for a frame (the CNN reads pixels as 0-255 itself)."""
    if spaces.frame is not None:
        return [1.0]
    bound = torch.maximum(spaces.low.abs(), spaces.high.abs())
    ok = torch.isfinite(bound) & (bound > 0)
    return torch.where(ok, 1.0 / torch.where(ok, bound, 1.0), 1.0).tolist()


def observation_net(
    spaces: TaskSpaces, cells: list[int], scale: list[float], outputs: int | None = None
) -> ActionMLP | ActionCNN:
    """A network from the observation to one value per action (Q, Deep TAMER's H^, PPO's logits) or to
    ``outputs`` values: an MLP on a vector, DQN's CNN on a frame."""
    out = spaces.actions if outputs is None else int(outputs)
    if spaces.frame is not None:
        return ActionCNN(spaces.frame, out, list(cells))
    return ActionMLP(spaces.observation_size, out, list(cells), scale)


def gym_env(task: GymTask, boards: int, seed: int) -> EnvBase:
    """``boards`` seeded copies of ``task`` with each episode's step count and return."""
    return TransformedEnv(
        make_gym_batch(task, boards, seed), Compose(StepCounter(), RewardSum()), auto_unwrap=True
    )


def observation(td: TensorDictBase) -> torch.Tensor:
    """What Q and H^ read of a step: the observation vector [B, S]."""
    return td.get(keys.OBSERVATION)


class GymTaskParts:
    """What every ``domain=gym`` learner reads of its task, each built once from ``cfg``: the task, its
    spaces and the inputs' scale (:func:`input_scale`)."""

    cfg: DictConfig

    @cached_property
    def task(self) -> GymTask:
        return make_gym_task(self.cfg)

    @cached_property
    def spaces(self) -> TaskSpaces:
        return gym_spaces(self.cfg)

    @cached_property
    def scale(self) -> list[float]:
        return input_scale(self.spaces)


class GymDQN(GymTaskParts, GymPage, DeepQLearner):
    """DQN over the observation of any discrete-action task on ``agent.boards`` copies (module docstring)."""

    domain = "gym"
    default_scaling = "none"  # Q + w H^ raw: with two actions, per-decision rescaling leaves R and H^ as 0
    # and 1 each (a weight below 1 never lets H^ overturn Q); "spread" equals raw while Q's gaps stay under 1

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_gym_dqn(cfg)

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        super().__init__(cfg, run_dir, checkpoint)
        if checkpoint is not None:
            self.load_page_state(checkpoint["state"])

    human_in_keys: ClassVar[list[Any]] = [keys.OBSERVATION]
    score_key = SCORE_KEY
    score_unit = "return per episode"
    episode_word = "episode"

    def make_wiring(self, run_dir: Path) -> FeedbackWiring:
        return self.page_wiring(run_dir, self.make_trainer)

    def make_env(self, boards: int, seed: int) -> EnvBase:
        return self.page_env(boards, seed)

    def domain_transforms(self) -> list[Transform]:
        return self.page_transforms()

    def make_dqn(self) -> DeepQ:
        q = observation_net(self.spaces, list(self.cfg.agent.cells), self.scale)
        return make_dqn(self.cfg, q, keys.OBSERVATION, None)

    def make_human(self) -> HumanValues:
        model = observation_net(self.spaces, list(self.cfg.human.cells), self.scale)
        return make_deep_tamer(self.cfg, model, observation, self.boards)

    def make_trainer(self, log: FeedbackLog) -> Trainer:
        return make_gym_trainer(self.cfg, self.spaces.actions, log)

    def make_feedback(self, trainer: Trainer, departure: Departure) -> Transform:
        return HumanFeedback(
            trainer, self.seconds_per_step, score_key=keys.EPISODE_REWARD, departure=departure
        )

    def watched_seconds(self, nxt: TensorDictBase) -> float:
        return self.watched_boards * self.seconds_per_step

    def start(self, logger: Logger) -> None:
        super().start(logger)
        self.announce_page()

    def advance(self) -> list[Point]:
        points = super().advance()
        self.show_points(points)
        return points

    def checkpoint(self) -> dict[str, Any]:
        out = super().checkpoint()
        out["state"].update(self.page_state())
        return out

    def episode_performance(self, nxt: TensorDictBase) -> torch.Tensor:
        return nxt[keys.EPISODE_REWARD].reshape(-1).to(torch.float64)

    def fusion_performance(self, performance: float) -> float:
        """The return above ``domain.min_return`` (0 below it): the trust factor and the bandit weigh
        episodes by a performance >= 0, and MountainCar's or Acrobot's returns are negative."""
        return max(0.0, performance - float(self.cfg.domain.min_return))

    def greedy_evaluation(self) -> dict[str, float]:
        return greedy_returns(self.task, self.eval_episodes, self.seed, self.greedy_policy, self.fusion)

    def policy_payload(self) -> dict[str, Any]:
        human = None
        if self.taught:
            h = self.cfg.human
            human = {"kind": "mlp", "cells": list(h.cells), "model": self.human.model.state_dict()}
        return export_policy(
            "gym_dqn",
            task=OmegaConf.to_container(self.cfg.domain, resolve=True),
            observation_size=self.spaces.observation_size,
            observation_shape=list(self.spaces.observation_shape),
            actions=self.spaces.actions,
            scale=list(self.scale),
            cells=list(self.cfg.agent.cells),
            q=self.dqn.model.state_dict(),
            fusion=self.fusion_payload(),
            human=human,
        )


def greedy_returns(task: GymTask, episodes: int, seed: int, policy: Any, fusion: Any) -> dict[str, float]:
    """A curve's point: ``policy`` played greedily on ``episodes`` fresh episodes of ``task`` (the run's
    ``eval_games`` seeds, the same at every point); the mean, median and 95 % interval of their returns."""
    env = gym_env(task, episodes, component_seed(seed, "eval_games"))
    try:
        returns = play_returns(env, policy, fusion)
    finally:
        env.close()
    s = summarize(returns)
    return {f"{SCORE_KEY}_{k}": s[k] for k in ("mean", "median", "ci95_low", "ci95_high")}


@torch.no_grad()
def play_returns(env: EnvBase, policy: Any, fusion: Any) -> torch.Tensor:
    """Every board of ``env`` (with ``RewardSum``) plays one episode greedily by ``policy`` (the fusion in
    evaluation mode); returns each episode's return [B] (float64)."""
    fusion.eval(True)
    try:
        td = env.reset()
        b = td.batch_size[0]
        returns = torch.zeros(b, dtype=torch.float64)
        finished = torch.zeros(b, dtype=torch.bool)
        while not bool(finished.all()):
            td, root = env.step_and_maybe_reset(policy(td))
            nxt = td["next"]
            done = nxt[keys.DONE].reshape(-1) & ~finished
            returns = torch.where(done, nxt[keys.EPISODE_REWARD].reshape(-1).to(torch.float64), returns)
            finished |= done
            td = root
        return returns
    finally:
        fusion.eval(False)
