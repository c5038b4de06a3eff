"""Q-learning on Tetris (thesis Algorithm 4): ``train.py agent=qlearning``.

Each placement on every board: choose epsilon-greedily, step the env (finished games restart), make the TD
update with the reward and the next state's placements. Each point adds the mean |TD error| of the game and
its exploration rate; at the end each learner's greedy policy plays ``agent.eval_games`` fresh games.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.agents.qlearning import LinearQLearning
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.experiment.checks import check_qlearning
from hfrl_torch.experiment.learners.tetris_games import TetrisGames


def epsilon_schedule(
    epsilon: float, decay: float, minimum: float, games_played: torch.Tensor
) -> torch.Tensor:
    """Exploration rate ``[L]`` of each learner's current game: max(epsilon * decay^games_played, minimum)."""
    return (epsilon * decay ** games_played.to(torch.float64)).clamp(min=minimum)


class QLearningLearner(TetrisGames):
    """L linear Q-learners over afterstate features, one board each."""

    agent = "qlearning"

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_qlearning(cfg)

    label = "Q-learning"

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        a = cfg.agent
        self.env_features = a.features
        self.agent_q = LinearQLearning(
            feature_size(feature_id(a.features), int(cfg.domain.width)),
            int(a.learners),
            a.alpha,
            a.gamma,
            seed=component_seed(cfg.seed, "agent"),
        )
        self.td_error = torch.zeros(int(a.learners), int(a.games), dtype=torch.float64)
        self.abs_delta = torch.zeros(int(a.learners), dtype=torch.float64)  # summed over the current game
        # read once: a config lookup costs more than the schedule, and this one is made every placement
        self.exploration = (float(a.epsilon), float(a.epsilon_decay), float(a.epsilon_min))
        super().__init__(cfg, run_dir, checkpoint)

    def epsilon(self, games: torch.Tensor) -> torch.Tensor:
        return epsilon_schedule(*self.exploration, games)

    def act(self, td: TensorDictBase, active: torch.Tensor) -> torch.Tensor:
        feats = td[keys.AFTERSTATE_FEATURES]
        return self.agent_q.act(
            feats, td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL], self.epsilon(self.played)
        )

    def observe(self, td: TensorDictBase, active: torch.Tensor) -> None:
        nxt = td["next"]
        chosen = td.get(keys.AFTERSTATE_FEATURES)[self.rows, td.get(keys.ACTION)]
        delta = self.agent_q.td_update(
            chosen,
            nxt[keys.REWARD].view(-1),
            nxt[keys.AFTERSTATE_FEATURES],
            nxt[keys.ACTION_MASK],
            nxt[keys.AFTERSTATE_TERMINAL],
            nxt[keys.TERMINATED].view(-1),
            active,
        )
        self.abs_delta += delta.abs()

    def game_ended(self, done: torch.Tensor, nxt: TensorDictBase) -> None:
        rows = done.nonzero().flatten()
        idx = self.played[rows]
        self.td_error[rows, idx] = self.abs_delta[rows] / self.pieces[rows, idx].clamp(min=1)
        self.abs_delta[rows] = 0.0

    def game_metrics(self, g: int) -> dict[str, float]:
        return {
            "train/td_error_mean": float(self.td_error[:, g].mean()),
            "train/epsilon": float(self.epsilon(torch.tensor(g))),
            "train/pieces_per_game": float(self.pieces[:, g].double().mean()),
        }

    def learner_state(self) -> dict[str, Any]:
        return {
            **self.agent_q.learner_state(),
            "td_error": self.td_error.clone(),
            "abs_delta": self.abs_delta.clone(),
        }

    def load_learner_state(self, state: dict[str, Any]) -> None:
        self.agent_q.load_learner_state(state)
        self.td_error, self.abs_delta = self.widen(state["td_error"]), state["abs_delta"].clone()

    def policy(self) -> dict[str, Any]:
        # Q(s, a) = w . f(s'_a) + b: the bias is the same for every placement, so argmax_a Q is the linear
        # afterstate policy w
        return self.linear_policy(self.env_features, self.agent_q.weight[0].detach(), "learner 0 of the run")

    def final(self) -> dict[str, Any]:
        final = super().final()
        if final and self.cfg.agent.eval_games > 0:
            final.update(
                self.greedy_evaluation(
                    self.agent_q.weight.detach(), self.env_features, self.cfg.agent.eval_games
                )
            )
            if self.logger is not None:
                self.logger.scalars(
                    {k: v for k, v in final.items() if k.startswith("eval/greedy")}, self.games
                )
        return final
