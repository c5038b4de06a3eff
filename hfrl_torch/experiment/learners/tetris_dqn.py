"""DQN on Tetris afterstates, alone or with a trainer's H^ fused: ``train.py agent=dqn [fusion=...]``.

Q(s, a) is one MLP over the features of placement a's afterstate (``agent.features``, BT by default, read as
the first columns of the env's features: Knox's 46 begin with BT's 21, so H^ over Knox and Q over BT share
one env). H^ is the linear TAMER model over the placement's feature change (``human=linear``) or Deep TAMER's
network over the same change (``human=mlp``). The curve's points are the greedy policy's lines per game on
``agent.eval_episodes`` fresh games (the same games at every point), capped at ``agent.eval_max_pieces``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.transforms import Transform

from hfrl_torch import keys
from hfrl_torch.agents.dqn import CHOOSABLE, DeepQ, HumanValues, SharedLinearTamer, choosable_module
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.tetris.features import feature_id, feature_names, feature_size
from hfrl_torch.experiment.checks import check_tetris_dqn
from hfrl_torch.experiment.factories import (
    make_deep_tamer,
    make_dqn,
    make_env,
    make_tamer,
    make_trainer,
)
from hfrl_torch.experiment.learners.deep_q import DeepQLearner
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.models.mlp import AfterstateMLP
from hfrl_torch.trainers import Trainer
from hfrl_torch.trainers.departure import Departure
from hfrl_torch.trainers.transform import HumanFeedback


def tetris_q_model(cfg: Any) -> AfterstateMLP:
    """The Q network of ``agent`` over the first ``agent.features`` columns, inputs scaled by 1 / height."""
    a = cfg.agent
    used = feature_size(feature_id(a.features), int(cfg.domain.width))
    return AfterstateMLP(used, list(a.cells), scale=1.0 / float(cfg.domain.height))


def tetris_human_model(cfg: Any) -> AfterstateMLP:
    """Deep TAMER's network over the placement's change of ``human.features``."""
    h = cfg.human
    return AfterstateMLP(
        feature_size(feature_id(h.features), int(cfg.domain.width)), list(h.cells), scale=h.scale
    )


class TetrisDQN(DeepQLearner):
    """DQN over Tetris afterstates on ``agent.boards`` boards (see the module docstring)."""

    domain = "tetris"

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_tetris_dqn(cfg)

    masked = True
    mask_key = CHOOSABLE
    human_in_keys: ClassVar[list[Any]] = [keys.AFTERSTATE_FEATURES, keys.STATE_FEATURES]
    score_key = "eval/greedy_lines"
    score_unit = "lines per game"
    episode_word = "game"

    @property
    def env_features(self) -> str:
        return (
            str(self.cfg.human.features) if self.cfg.trainer.name != "none" else str(self.cfg.agent.features)
        )

    def make_env(self, boards: int, seed: int) -> EnvBase:
        env = make_env(self.cfg, boards, features=self.env_features)
        env.set_seed(seed)
        return env

    def make_dqn(self) -> DeepQ:
        return make_dqn(
            self.cfg, tetris_q_model(self.cfg), keys.AFTERSTATE_FEATURES, CHOOSABLE, (choosable_module(),)
        )

    def make_human(self) -> HumanValues:
        h, width = self.cfg.human, int(self.cfg.domain.width)
        if h.name == "mlp":
            return make_deep_tamer(self.cfg, tetris_human_model(self.cfg), placement_deltas, self.boards)
        return SharedLinearTamer(
            make_tamer(self.cfg, self.boards, feature_size(feature_id(h.features), width))
        )

    def make_trainer(self, log: FeedbackLog) -> Trainer:
        return make_trainer(self.cfg, log)

    def make_feedback(self, trainer: Trainer, departure: Departure) -> Transform:
        return HumanFeedback(trainer, float(self.cfg.human.seconds_per_placement), departure=departure)

    def watched_seconds(self, nxt: TensorDictBase) -> float:
        return self.boards * float(self.cfg.human.seconds_per_placement)

    def episode_performance(self, nxt: TensorDictBase) -> torch.Tensor:
        return nxt[keys.LINES].reshape(-1).to(torch.float64)

    def greedy_evaluation(self) -> dict[str, float]:
        games = self.eval_episodes
        env = make_env(
            self.cfg, games, features=self.env_features, max_pieces=int(self.cfg.agent.eval_max_pieces)
        )
        env.set_seed(component_seed(self.seed, "eval_games"))
        lines, _ = play_games(env, self.greedy_policy, self.fusion)
        s = summarize(lines, floor=0.0)
        return {f"{self.score_key}_{k}": s[k] for k in ("mean", "median", "ci95_low", "ci95_high")}

    def policy_payload(self) -> dict[str, Any]:
        a, width = self.cfg.agent, int(self.cfg.domain.width)
        payload: dict[str, Any] = {
            "env_features": self.env_features,
            "features": str(a.features),
            "feature_names": feature_names(feature_id(str(a.features)), width),
            "cells": list(a.cells),
            "q": self.dqn.model.state_dict(),
            "fusion": self.fusion_payload(),
        }
        if self.taught:
            h = self.cfg.human
            human: dict[str, Any] = {"kind": str(h.name), "features": str(h.features)}
            if h.name == "mlp":
                human.update(cells=list(h.cells), scale=float(h.scale), model=self.human.model.state_dict())
            else:
                human["weights"] = self.human.weight.detach().clone()
            payload["human"] = human
        return export_policy("tetris_dqn", **payload)


@torch.no_grad()
def play_games(env: EnvBase, policy: Any, fusion: Any) -> tuple[torch.Tensor, torch.Tensor]:
    """Every board of ``env`` plays one game greedily by ``policy`` (the fusion in evaluation mode); returns
    the lines and the pieces of each game [B] (float64)."""
    fusion.eval(True)
    try:
        td = env.reset()
        b = td.batch_size[0]
        lines = torch.zeros(b, dtype=torch.float64)
        pieces = torch.zeros(b, dtype=torch.float64)
        finished = torch.zeros(b, dtype=torch.bool)
        while not bool(finished.all()):
            td = env.step(policy(td))
            nxt = td["next"]
            done = nxt[keys.DONE].reshape(-1) & ~finished
            lines = torch.where(done, nxt[keys.LINES].reshape(-1).to(torch.float64), lines)
            pieces = torch.where(done, nxt[keys.PIECES_PLACED].reshape(-1).to(torch.float64), pieces)
            finished |= done
            td = nxt.exclude(keys.REWARD, keys.DONE, keys.TERMINATED, keys.TRUNCATED)
        return lines, pieces
    finally:
        fusion.eval(False)
