"""The deciding keeper's state variables (Stone, Sutton & Kuhlmann 2005) and the optional
quantised view of the server's visual sensor.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.physics import direction, norm, unit, wrap_angle

DISTANCE_QUANTUM = 0.1  # server quantize_step for players and ball
_EPS = 1e-10


def gather_points(points: Tensor, index: Tensor) -> Tensor:
    """``points[b, index[b, ...]]`` for points [B, P, 2] and index [B, ...]."""
    flat = index.reshape(index.shape[0], -1)
    picked = torch.gather(points, 1, flat.unsqueeze(-1).expand(-1, -1, 2))
    return picked.reshape(*index.shape, 2)


def angle_at_vertex(vertex: Tensor, a: Tensor, b: Tensor) -> Tensor:
    """Angle a-vertex-b in degrees, in [0, 180]."""
    va = a - vertex
    vb = b - vertex
    cross = va[..., 0] * vb[..., 1] - va[..., 1] * vb[..., 0]
    return torch.rad2deg(torch.atan2(cross.abs(), (va * vb).sum(-1)))


def quantised_view(observer_pos: Tensor, observer_body: Tensor, points: Tensor) -> Tensor:
    """Positions [B, K, 2] as the server's visual sensor reports them to the observer [B, 2].

    Distance d becomes round(exp(round(log(d), 0.1)), 0.1) (about +-5 %) and the direction
    relative to the body is rounded to whole degrees.
    """
    rel = points - observer_pos.unsqueeze(-2)
    dist = norm(rel)
    qlog = torch.round(torch.log(dist + _EPS) / DISTANCE_QUANTUM) * DISTANCE_QUANTUM
    qdist = torch.round(torch.exp(qlog) / 0.1) * 0.1
    rel_dir = wrap_angle(direction(rel) - observer_body.unsqueeze(-1))
    qdir = torch.deg2rad(torch.round(torch.rad2deg(rel_dir)))
    seen = observer_pos.unsqueeze(-2) + qdist.unsqueeze(-1) * unit(qdir + observer_body.unsqueeze(-1))
    return torch.where((dist > 0).unsqueeze(-1), seen, points)


def teammate_order(keeper_pos: Tensor, decider: Tensor) -> Tensor:
    """Indices [B, n-1] of the decider's teammates, nearest first (ties: lower index)."""
    k1 = gather_points(keeper_pos, decider.unsqueeze(-1))  # [B, 1, 2]
    dist = norm(keeper_pos - k1)
    dist = dist.scatter(1, decider.unsqueeze(-1), math.inf)
    order = torch.sort(dist, dim=1, stable=True).indices
    return order[:, :-1]


def keeper_state_variables(
    keeper_pos: Tensor, taker_pos: Tensor, decider: Tensor, centre: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """State variables [B, 4n + 2m - 3] of keeper ``decider`` [B], in the spec's order.

    dist(K1,C); dist(K1,Ki) i>=2; dist(K1,Tj); dist(Ki,C) i>=2; dist(Tj,C);
    min_j dist(Ki,Tj) i>=2; min_j ang(Ki,K1,Tj) (degrees) i>=2. Teammates and takers are
    numbered by distance to K1.

    :returns: the state variables and the teammate order [B, n-1] (keeper indices).
    """
    if centre is None:
        centre = torch.zeros(2, device=keeper_pos.device, dtype=keeper_pos.dtype)
    order = teammate_order(keeper_pos, decider)
    k1 = gather_points(keeper_pos, decider.unsqueeze(-1))  # [B, 1, 2]
    mates = gather_points(keeper_pos, order)  # [B, n-1, 2]
    taker_dist = norm(taker_pos - k1)
    taker_sorted = torch.sort(taker_dist, dim=1, stable=True)
    takers = gather_points(taker_pos, taker_sorted.indices)  # [B, m, 2]
    k1_flat = k1.squeeze(-2)
    mate_taker_dist = norm(mates.unsqueeze(-2) - takers.unsqueeze(-3))  # [B, n-1, m]
    mate_taker_ang = angle_at_vertex(k1.unsqueeze(-2), mates.unsqueeze(-2), takers.unsqueeze(-3))
    state = torch.cat(
        (
            norm(k1_flat - centre).unsqueeze(-1),
            norm(mates - k1),
            taker_sorted.values,
            norm(mates - centre),
            norm(takers - centre),
            mate_taker_dist.min(-1).values,
            mate_taker_ang.min(-1).values,
        ),
        dim=-1,
    )
    return state, order
