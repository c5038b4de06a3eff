"""TAMER on Tetris with a trainer in the loop (thesis Algorithms 1-3): ``train.py agent=tamer``.

Each placement on every board: H^ learns from the feedback due on the simulated clock, the learner places
greedily under H^ (the fusion component's ``human_only`` rule: argmax H^), the trainer judges the placement
and its events go into the feedback channel. The points add the feedback given in each game. Every event
is appended to ``feedback.jsonl`` as it is given. Because f(s) is the same for every placement, argmax_a H^
is a linear afterstate policy, so a TAMER checkpoint plays in ``evaluate.py`` like a CE one (learner 0).
"""

from __future__ import annotations

from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.experiment.checks import check_tamer
from hfrl_torch.experiment.learners.tetris_games import TetrisGames


class TamerLearner(TetrisGames):
    """L TAMER learners over Knox's (or the BT) feature changes, one board and one trainer each."""

    agent = "tamer"

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_tamer(cfg)

    label = "TAMER"
    taught = True
    select = "greedy"
    fusion_option = "human_only"  # TAMER acts on H^ alone

    @property
    def env_features(self) -> str:  # type: ignore[override]
        return str(self.cfg.human.features)

    def act(self, td: TensorDictBase, active: torch.Tensor) -> torch.Tensor:
        td.set(keys.HUMAN_VALUES, self.human_values(td))
        return self.fuse(td).get(keys.ACTION)

    def game_metrics(self, g: int) -> dict[str, float]:
        return self.feedback_metrics(g)

    def policy(self) -> dict[str, Any]:
        # argmax_a w.(f(s'_a) - f(s)) = argmax_a w.f(s'_a): H^ acts as a linear afterstate policy
        return self.linear_policy(
            self.env_features, self.human.model.weight[0].detach(), "learner 0 of the run"
        )
