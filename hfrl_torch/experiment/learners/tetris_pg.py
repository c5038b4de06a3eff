"""Policy gradient on Tetris, alone or with a trainer (thesis Figures 3.5 and 4.2): ``train.py agent=pg``.

Each placement on every board: sample from each learner's softmax policy over the placements, add the
score (and the Fisher matrix) to its game in progress, step the env, and close the games that ended with
their lines as the return; a learner steps its weights every ``agent.games_per_update`` games. With a
trainer (one simulated trainer per learner), H^ learns from its feedback and the policy samples from
pi ~ exp(f(R, H^) / T), f the fusion component's rule on R = theta . f(s'_a): ``linear`` gives
theta . f + w H^, w the learner's weight (trust factor: eq. 4.4 after each of its games, from the game's lines
and its match rate; or annealed). The points add the pieces per game and, with a trainer, the feedback
given, the weight and the match rate; at the end each learner's greedy policy plays fresh games.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.agents.pg import PolicyGradient
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.experiment.checks import check_pg
from hfrl_torch.experiment.learners.tetris_games import TetrisGames


class PolicyGradientLearner(TetrisGames):
    """L policy-gradient learners, one board each (and one trainer each with a trainer)."""

    agent = "pg"
    default_scaling = "none"  # H^ biases the logits as they are

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_pg(cfg)

    taught = True

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        a = cfg.agent
        self.n_pg = feature_size(feature_id(a.features), int(cfg.domain.width))
        self.pg = PolicyGradient(
            self.n_pg,
            int(a.learners),
            a.lr,
            a.temperature,
            a.natural,
            a.damping,
            a.games_per_update,
            a.baseline_decay,
            seed=component_seed(cfg.seed, "agent"),
        )
        L, G = int(a.learners), int(a.games)
        self.used_weight = torch.zeros(L, G, dtype=torch.float64)
        self.match_rate = torch.full((L, G), math.nan, dtype=torch.float64)
        super().__init__(cfg, run_dir, checkpoint)

    @property
    def label(self) -> str:  # type: ignore[override]
        return "natural PG" if self.cfg.agent.natural else "PG"

    @property
    def env_features(self) -> str:  # type: ignore[override]
        return (
            str(self.cfg.human.features) if self.cfg.trainer.name != "none" else str(self.cfg.agent.features)
        )

    def act(self, td: TensorDictBase, active: torch.Tensor) -> torch.Tensor:
        feats = td[keys.AFTERSTATE_FEATURES][..., : self.n_pg]
        mask, terminal = td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL]
        values = None
        if self.trainer is not None:
            td.set(keys.ENV_VALUES, self.pg.values(feats))
            td.set(keys.HUMAN_VALUES, self.human_values(td))
            self.fuse(td)
            values = td.get(keys.FUSED_VALUES)
            rows = self.rows
            g = self.played.clamp(max=self.games - 1)
            self.used_weight[rows, g] = torch.where(
                active, td.get(keys.FUSION_WEIGHT), self.used_weight[rows, g]
            )
        action = self.pg.act(feats, mask, terminal, values)
        self.pg.record(feats, mask, terminal, action, active, values)
        return action

    def game_ended(self, done: torch.Tensor, nxt: TensorDictBase) -> None:
        game_lines = nxt[keys.LINES].view(-1)
        self.pg.end_games(done, game_lines.to(torch.float64))
        if self.trainer is not None:
            rows = done.nonzero().flatten()
            self.match_rate[rows, self.played[rows]] = self.fusion.matches.rates()[rows]
            taught = self.given[self.rows, self.played.clamp(max=self.games - 1), 0] > 0
            self.fusion.end_episode(done, game_lines.to(torch.float64), taught)

    def game_metrics(self, g: int) -> dict[str, float]:
        metrics = {"train/pieces_per_game": float(self.pieces[:, g].double().mean())}
        if self.trainer is not None:
            m = self.match_rate[:, g]
            metrics.update(
                {
                    **self.feedback_metrics(g),
                    "fusion/weight_mean": float(self.used_weight[:, g].mean()),
                    "fusion/match_rate_mean": float(m[~m.isnan()].mean())
                    if bool((~m.isnan()).any())
                    else math.nan,
                }
            )
        return metrics

    def learner_state(self) -> dict[str, Any]:
        return {
            **self.pg.learner_state(),
            "used_weight": self.used_weight.clone(),
            "match_rate": self.match_rate.clone(),
        }

    def load_learner_state(self, state: dict[str, Any]) -> None:
        self.pg.load_learner_state(state)
        self.used_weight, self.match_rate = (
            self.widen(state["used_weight"]),
            self.widen(state["match_rate"], math.nan),
        )

    def policy(self) -> dict[str, Any]:
        # evaluate.py plays theta greedily: the most probable placement of the softmax policy
        return self.linear_policy(
            str(self.cfg.agent.features), self.pg.weight[0].detach(), "learner 0 of the run, played greedily"
        )

    def final(self) -> dict[str, Any]:
        final = super().final()
        if final and self.cfg.agent.eval_games > 0:
            final.update(
                self.greedy_evaluation(
                    self.pg.weight.detach(), str(self.cfg.agent.features), self.cfg.agent.eval_games
                )
            )
            if self.logger is not None:
                self.logger.scalars(
                    {k: v for k, v in final.items() if k.startswith("eval/greedy")}, self.games
                )
        return final
