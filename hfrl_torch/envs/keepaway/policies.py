"""The benchmark keeper policies of Stone, Sutton & Kuhlmann (2005): Random, Always Hold and
Hand-coded. Each maps the deciding keepers' state variables [B, F] to actions [B]
(0 = HoldBall, k = PassBall to the k-th nearest teammate)."""

from __future__ import annotations

from typing import Protocol

import torch
from torch import Tensor

POLICIES = ("random", "hold", "hand")
HAND_HOLD_SCORE = 90.0
HAND_DIST_WEIGHT = 4.0
HAND_SAFE_DISTANCE = 5.0


class KeeperPolicy(Protocol):
    """A keeper policy: state variables [B, F] -> actions [B]."""

    def __call__(self, obs: Tensor) -> Tensor: ...


def hold_actions(obs: Tensor) -> Tensor:
    """Always Hold."""
    return torch.zeros(obs.shape[0], dtype=torch.long, device=obs.device)


def random_actions(obs: Tensor, num_actions: int, generator: torch.Generator | None = None) -> Tensor:
    """Random: uniform over HoldBall and the passes."""
    return torch.randint(0, num_actions, (obs.shape[0],), generator=generator, device=obs.device)


def hand_coded_actions(obs: Tensor, keepers: int, takers: int) -> Tensor:
    """Hand-coded: hold if the nearest taker is more than 5 m away; else score hold at 90 and
    pass k at 4 * min_j dist(Kk, Tj) + min_j ang(Kk, K1, Tj) and take the best (ties: hold,
    then the nearer teammate)."""
    n, m = keepers, takers
    nearest_taker = obs[:, n]
    start = 2 * n + 2 * m - 1
    open_dist = obs[:, start : start + n - 1]
    open_ang = obs[:, start + n - 1 : start + 2 * n - 2]
    scores = torch.cat(
        (
            torch.full_like(open_dist[:, :1], HAND_HOLD_SCORE),
            HAND_DIST_WEIGHT * open_dist + open_ang,
        ),
        dim=1,
    ).float()
    best = torch.argmax(scores, dim=1)
    return torch.where(nearest_taker > HAND_SAFE_DISTANCE, torch.zeros_like(best), best)


def make_benchmark_policy(
    name: str, keepers: int, takers: int, generator: torch.Generator | None = None
) -> KeeperPolicy:
    """The benchmark policy called ``name`` ("random", "hold" or "hand")."""
    if name == "hold":
        return hold_actions
    if name == "random":
        return lambda obs: random_actions(obs, keepers, generator)
    if name == "hand":
        return lambda obs: hand_coded_actions(obs, keepers, takers)
    raise ValueError(f"unknown benchmark policy {name!r}; expected one of {POLICIES}")
