"""Hashed one-dimensional tile coding with a learner batch dimension (Stone, Sutton & Kuhlmann 2005).

For every state variable v and action a there are T = 32 one-dimensional tilings of tile width
``widths[v]``; tiling j is offset by j / T of a tile width. In each tiling the state lies in exactly
one tile, so an action has N = F * T active tiles (416 for the 13 variables of 3v2 keepaway).
Each tile, named by (action, variable, tiling, tile coordinate), is hashed into a table of
``size`` weights (2^20 in the reference), and Q(s, a) is the sum of the weights of a's active tiles.

The tile coordinate follows Sutton's ``tiles()`` (``GetTiles1``) that the keepaway players call with
``state[v] / width[v]``: q = floor(x * T) and, in tiling j, the tile is floor((q - j) / T), i.e. the
tile boundaries of tiling j lie at (j / T + k) widths. Only the hash function differs from the
reference (a fixed two-round multiply-xor hash here, Sutton's UNH hash with a collision table
there); tiles that collide share a weight, as in any hashed tile coder.

Weights are ``[L, size]``: one table per independent learner, so many learners (every keeper of
every field, i.e. every seed of an experiment) live in one module. Reads gather the active weights
and updates use ``index_add_``; nothing dense over the table is ever computed.

Example:
    >>> coder = TileCoding(widths=[2.0], num_actions=2, learners=1, tilings=4, size=64)
    >>> tiles = coder.tiles(torch.tensor([[1.0]]))  # [M=1, A=2, N=4]
    >>> tiles.shape, bool(((tiles >= 0) & (tiles < 64)).all())
    (torch.Size([1, 2, 4]), True)
    >>> coder.add_(torch.tensor([0]), tiles[:, 0], torch.full((1, 4), 0.5))
    >>> coder(torch.tensor([0]), tiles).tolist()
    [[2.0, 0.0]]
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

DEFAULT_TILINGS = 32
DEFAULT_SIZE = 2**20
MAX_SIZE = 2**30

# Keepaway state-variable tile widths of the reference players (metres, degrees), from
# WorldModel::keeperStateRangesAndResolutions with its C++ integer divisions.
KEEPAWAY_ANGLE_WIDTH = 10.0
KEEPAWAY_OPEN_DISTANCE_WIDTH = 4.0
KEEPAWAY_TAKER_CENTRE_WIDTH = 3.0

_PRIME = 2**31 - 1  # Mersenne prime: every product below stays < 2^62, so int64 never overflows
_MUL1, _ADD1 = 1_103_515_245, 12_345
_MUL2, _ADD2 = 2_147_483_629, 1_013_904_223


def _trunc_div(a: int, b: int) -> int:
    """C++ integer division (truncates toward zero), as in the reference's width formulas."""
    return int(a / b)


def keepaway_tile_widths(keepers: int = 3, takers: int = 2) -> list[float]:
    """Tile widths of the 4n + 2m - 3 keeper state variables, in the spec's order.

    3v2 gives 2, 2, 3, 2, 3, 2, 3, 3, 3 (m), 4, 4 (m), 10, 10 (degrees), the spec's values; other
    team sizes follow the reference formulas (needs n >= 3 keepers and m >= 2 takers).
    """
    n, m = keepers, takers
    if n < 3 or m < 2:
        raise ValueError(f"keepaway tile widths need keepers >= 3 and takers >= 2, got {n} and {m}")
    widths = [2.0]  # dist(K1, C)
    widths += [2.0 + _trunc_div(i - 1, n - 2) for i in range(1, n)]  # dist(K1, Ki)
    widths += [3.0 + _trunc_div(i - 1, m - 1) for i in range(m)]  # dist(K1, Tj)
    widths += [2.0 + _trunc_div(i - 1, n - 2) for i in range(1, n)]  # dist(Ki, C)
    widths += [KEEPAWAY_TAKER_CENTRE_WIDTH] * m  # dist(Tj, C)
    widths += [KEEPAWAY_OPEN_DISTANCE_WIDTH] * (n - 1)  # min_j dist(Ki, Tj)
    widths += [KEEPAWAY_ANGLE_WIDTH] * (n - 1)  # min_j ang(Ki, K1, Tj)
    return widths


def tile_coordinates(values: torch.Tensor, widths: torch.Tensor, tilings: int) -> torch.Tensor:
    """Tile coordinates ``[..., F, T]`` (int64) of state variables ``values`` ``[..., F]``.

    Coordinate in tiling j = floor((floor(x * T) - j) / T) with x = value / width: tilings offset by
    1/T of a width, negative values included (floor, not truncation).
    """
    x = values.to(torch.float64) / widths.to(device=values.device, dtype=torch.float64)
    q = torch.floor(x * tilings).to(torch.int64).unsqueeze(-1)
    j = torch.arange(tilings, dtype=torch.int64, device=values.device)
    return torch.div(q - j, tilings, rounding_mode="floor")


def hash_tiles(coordinates: torch.Tensor, num_actions: int, size: int) -> torch.Tensor:
    """Hashed indices ``[..., A, F * T]`` in ``[0, size)`` of coordinates ``[..., F, T]``.

    The key of a tile is coordinate * (A F T) + (a F + v) T + j, unique per (action, variable,
    tiling, coordinate); two rounds of multiply-add modulo 2^31 - 1 with an xor-shift in between
    spread it over the table.
    """
    if not 1 <= size <= MAX_SIZE:
        raise ValueError(f"tile-coding size must be in 1..{MAX_SIZE}, got {size}")
    *lead, f, t = coordinates.shape
    device = coordinates.device
    group = torch.arange(num_actions * f * t, dtype=torch.int64, device=device).view(num_actions, f * t)
    key = coordinates.reshape(*lead, 1, f * t) * (num_actions * f * t) + group
    h = torch.remainder(key, _PRIME)
    h = (h * _MUL1 + _ADD1) % _PRIME
    h = h ^ (h >> 15)
    h = (h * _MUL2 + _ADD2) % _PRIME
    return h % size


class TileCoding(nn.Module):
    """Q(s, a) = sum of the weights of a's active tiles, one hashed weight table per learner.

    :param widths: tile width of each of the F state variables.
    :param num_actions: A, the number of actions (each action has its own tiles).
    :param learners: L independent weight tables.
    :param tilings: T one-dimensional tilings per state variable (32 in the reference).
    :param size: weights per learner (2^20 in the reference); hashed indices stay in [0, size).
    :param dtype: weight dtype (float32: 4 MiB per learner at 2^20).
    """

    def __init__(
        self,
        widths: Sequence[float],
        num_actions: int,
        learners: int = 1,
        tilings: int = DEFAULT_TILINGS,
        size: int = DEFAULT_SIZE,
        dtype: torch.dtype = torch.float32,
        device: str | torch.device = "cpu",
    ) -> None:
        super().__init__()
        if len(widths) < 1 or min(widths) <= 0 or not all(math.isfinite(w) for w in widths):
            raise ValueError(f"tile widths must be finite and > 0, got {list(widths)}")
        if num_actions < 1 or learners < 1 or tilings < 1:
            raise ValueError(
                f"need num_actions, learners, tilings >= 1, got {num_actions}, {learners}, {tilings}"
            )
        if not 1 <= size <= MAX_SIZE:
            raise ValueError(f"tile-coding size must be in 1..{MAX_SIZE}, got {size}")
        self.num_actions = num_actions
        self.tilings = tilings
        self.size = size
        self.register_buffer("widths", torch.tensor(list(widths), dtype=torch.float64, device=device))
        self.register_buffer("weight", torch.zeros(learners, size, dtype=dtype, device=device))

    @property
    def learners(self) -> int:
        return self.weight.shape[0]

    @property
    def num_features(self) -> int:
        return self.widths.shape[0]

    @property
    def active_tiles(self) -> int:
        """N = F * T, the number of active tiles of one action (416 in 3v2)."""
        return self.num_features * self.tilings

    def tiles(self, values: torch.Tensor) -> torch.Tensor:
        """Active tile indices ``[M, A, N]`` (int64, in [0, size)) of state variables ``[M, F]``."""
        if values.shape[-1] != self.num_features:
            raise ValueError(f"expected {self.num_features} state variables, got shape {tuple(values.shape)}")
        return hash_tiles(tile_coordinates(values, self.widths, self.tilings), self.num_actions, self.size)

    def _flat(self, learners: torch.Tensor, tiles: torch.Tensor) -> torch.Tensor:
        offset = learners.to(torch.int64) * self.size
        return tiles + offset.view(-1, *([1] * (tiles.dim() - 1)))

    def forward(self, learners: torch.Tensor, tiles: torch.Tensor) -> torch.Tensor:
        """Sums ``[M, ...]`` of learner ``learners[m]``'s weights over ``tiles`` ``[M, ..., N]``."""
        flat = self._flat(learners, tiles)
        return self.weight.view(-1).index_select(0, flat.reshape(-1)).view(flat.shape).sum(-1)

    @torch.no_grad()
    def add_(self, learners: torch.Tensor, indices: torch.Tensor, values: torch.Tensor) -> None:
        """``weight[learners[m], indices[m, k]] += values[m, k]`` (repeated indices add up)."""
        flat = self._flat(learners, indices).reshape(-1)
        self.weight.view(-1).index_add_(0, flat, values.reshape(-1).to(self.weight.dtype))
