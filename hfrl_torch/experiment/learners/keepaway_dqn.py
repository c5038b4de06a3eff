"""DQN keepers, alone or with a trainer's H^ fused (``train.py agent=dqn domain=keepaway [fusion=...]``).

Each field is one SMDP for the team (``agents.dqn.TeamSteps``): ``KeepawayEnv(sync="all")`` steps every field
to its next decision, whichever keeper has the ball, and the reward is the step's simulated seconds. Q is one
MLP from the deciding keeper's 4n + 2m - 3 state variables to Hold and each pass (inputs scaled by ten tile
widths: distances / 20-40 m, angles / 100 degrees). H^ is the tile-coded TAMER model on the same variables
(``human=tile_coded``) or Deep TAMER's network on them (``human=mlp``); a simulated trainer per field judges
the deciding keeper against the hand-coded keepers, its events credited over the field's clock. The points
are the greedy keepers' episode seconds on ``agent.eval_episodes`` fresh episodes (the same at every point).
"""

from __future__ import annotations

from dataclasses import asdict
from functools import cached_property
from typing import Any, ClassVar

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.transforms import Transform

from hfrl_torch import keys
from hfrl_torch.agents.dqn import DeepQ, HumanValues, TeamSteps
from hfrl_torch.agents.dqn.team_steps import CYCLES_PER_SECOND
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv
from hfrl_torch.experiment.checks import check_keepaway_dqn
from hfrl_torch.experiment.factories import (
    make_deep_tamer,
    make_dqn,
    make_keepaway_config,
    make_keeper_trainer,
    make_shared_tile_tamer,
)
from hfrl_torch.experiment.learners.deep_q import DeepQLearner
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.models.mlp import ActionMLP, keeper_scale
from hfrl_torch.trainers.departure import Departure
from hfrl_torch.trainers.keepaway_oracle import KeepawayOracle
from hfrl_torch.trainers.keepaway_replay import KeepawayReplay
from hfrl_torch.trainers.keeper_transform import KeeperFeedback


def keepaway_q_model(cfg: Any, config: KeepawayConfig) -> ActionMLP:
    """The Q network of ``agent``: state variables to one value per action."""
    return ActionMLP(config.num_state_vars, config.num_actions, list(cfg.agent.cells), keeper_scale(config))


def keepaway_human_model(cfg: Any, config: KeepawayConfig) -> ActionMLP:
    """Deep TAMER's network: state variables to H^ of each action."""
    return ActionMLP(config.num_state_vars, config.num_actions, list(cfg.human.cells), keeper_scale(config))


def _observation(td: TensorDictBase) -> torch.Tensor:
    return td.get(keys.OBSERVATION)


class KeepawayDQN(DeepQLearner):
    """DQN keepers on ``agent.boards`` fields of one learner (see the module docstring)."""

    domain = "keepaway"
    default_scaling = "spread"  # H^ times Q's running spread, as the Sarsa keepers

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_keepaway_dqn(cfg)

    human_in_keys: ClassVar[list[Any]] = [keys.OBSERVATION]
    score_key = "eval/greedy_episode_seconds"
    score_unit = "s per episode"
    episode_word = "episode"

    @cached_property
    def config(self) -> KeepawayConfig:
        return make_keepaway_config(self.cfg)

    def make_env(self, boards: int, seed: int) -> EnvBase:
        return KeepawayEnv(boards, self.config, seed=seed, sync="all")

    def domain_transforms(self) -> list[Transform]:
        return [TeamSteps()]

    def make_dqn(self) -> DeepQ:
        return make_dqn(self.cfg, keepaway_q_model(self.cfg, self.config), keys.OBSERVATION, keys.ACTION_MASK)

    def make_human(self) -> HumanValues:
        if self.cfg.human.name == "mlp":
            return make_deep_tamer(
                self.cfg, keepaway_human_model(self.cfg, self.config), _observation, self.boards
            )
        return make_shared_tile_tamer(self.cfg, self.config, self.boards)

    def make_trainer(self, log: FeedbackLog) -> KeepawayOracle | KeepawayReplay:
        return make_keeper_trainer(self.cfg, self.config, self.boards, log)

    def make_feedback(self, trainer: KeepawayOracle | KeepawayReplay, departure: Departure) -> Transform:
        return KeeperFeedback(trainer, departure=departure)

    def watched_seconds(self, nxt: TensorDictBase) -> float:
        return float(nxt[keys.STEP_CYCLES].sum()) / CYCLES_PER_SECOND

    def episode_performance(self, nxt: TensorDictBase) -> torch.Tensor:
        return nxt[keys.EPISODE_CYCLES].reshape(-1).to(torch.float64) / CYCLES_PER_SECOND

    def greedy_evaluation(self) -> dict[str, float]:
        env = KeepawayEnv(
            self.eval_episodes, self.config, seed=component_seed(self.seed, "eval_games"), sync="all"
        )
        seconds, _ = play_episodes(env, self.greedy_policy, self.fusion)
        s = summarize(seconds, floor=0.0)
        return {f"{self.score_key}_{k}": s[k] for k in ("mean", "median", "ci95_low", "ci95_high")}

    def policy_payload(self) -> dict[str, Any]:
        payload: dict[str, Any] = {
            "cells": list(self.cfg.agent.cells),
            "q": self.dqn.model.state_dict(),
            "fusion": self.fusion_payload(),
        }
        if self.taught:
            h = self.cfg.human
            if h.name == "mlp":
                payload["human"] = {
                    "kind": "mlp",
                    "cells": list(h.cells),
                    "model": self.human.model.state_dict(),
                }
            else:
                coder = self.human.coder
                payload["human"] = {
                    "kind": "tile_coded",
                    "tilings": coder.tilings,
                    "size": coder.size,
                    "weights": coder.weight.detach().clone(),
                }
        return export_policy("keepaway_dqn", **payload)

    def checkpoint(self) -> dict[str, Any]:
        return {**super().checkpoint(), "domain_config": asdict(self.config)}


@torch.no_grad()
def play_episodes(env: EnvBase, policy: Any, fusion: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Every field of ``env`` plays one episode greedily by ``policy`` (the fusion in evaluation mode);
    returns each episode's seconds [B] (float64) and how it ended [B] (1 out of bounds, 2 taken)."""
    fusion.eval(True)
    try:
        td = env.reset()
        b = td.batch_size[0]
        seconds = torch.zeros(b, dtype=torch.float64)
        cause = torch.zeros(b, dtype=torch.int64)
        finished = torch.zeros(b, dtype=torch.bool)
        while not bool(finished.all()):
            td = env.step(policy(td))
            nxt = td["next"]
            done = nxt[keys.DONE].reshape(-1) & ~finished
            cycles = nxt[keys.EPISODE_CYCLES].reshape(-1).to(torch.float64)
            seconds = torch.where(done, cycles / CYCLES_PER_SECOND, seconds)
            cause = torch.where(done, nxt[keys.END_CAUSE].reshape(-1).to(torch.int64), cause)
            finished |= done
            td = nxt.exclude(keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)
        return seconds, cause
    finally:
        fusion.eval(False)
