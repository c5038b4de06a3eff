"""Compiled (numba) twins of :class:`~hfrl_torch.models.tile_coding.TileCoding`'s tile indices, Q and
updates, for the CPU at small batches where torch's per-call overhead dominates.

:func:`tile_indices` equals ``TileCoding.tiles`` bit for bit (the same float64 coordinates, floor
division and int64 hash). :func:`table_sums` and :func:`table_add` read and write the weight table in
place through a numpy view of the module's ``weight`` buffer, so the module stays the one truth.
Sums accumulate in float64 and round once to the table's dtype: torch's float32 ``sum`` (vectorised
partial sums) agrees within float32 rounding, not bit for bit.
"""

from __future__ import annotations

import math

import numba
import numpy as np
import torch

from hfrl_torch.models.tile_coding import _ADD1, _ADD2, _MUL1, _MUL2, _PRIME, TileCoding

_JIT = numba.njit(cache=True, nogil=True)


@_JIT
def tile_row(
    values: np.ndarray, widths: np.ndarray, tilings: int, num_actions: int, size: int, out: np.ndarray
):
    """Active tiles ``out`` [A, F * T] of one state ``values`` [F] (float64): ``hash_tiles(tile_coordinates)``
    of ``tile_coding``, the same int64 arithmetic."""
    f = widths.shape[0]
    group_size = f * tilings
    span = num_actions * group_size
    for v in range(f):
        q = np.int64(math.floor((values[v] / widths[v]) * tilings))
        for j in range(tilings):
            coordinate = (q - j) // tilings
            for a in range(num_actions):
                key = coordinate * span + (a * f + v) * tilings + j
                h = key % _PRIME
                h = (h * _MUL1 + _ADD1) % _PRIME
                h = h ^ (h >> 15)
                h = (h * _MUL2 + _ADD2) % _PRIME
                out[a, v * tilings + j] = h % size


@_JIT
def tile_indices(
    values: np.ndarray, widths: np.ndarray, tilings: int, num_actions: int, size: int
) -> np.ndarray:
    """Active tiles [M, A, F * T] (int64) of states ``values`` [M, F] (float64)."""
    m = values.shape[0]
    out = np.empty((m, num_actions, widths.shape[0] * tilings), dtype=np.int64)
    for r in range(m):
        tile_row(values[r], widths, tilings, num_actions, size, out[r])
    return out


@_JIT
def table_sums(weight: np.ndarray, tables: np.ndarray, tiles: np.ndarray, out: np.ndarray) -> None:
    """``out[m, k] = sum_n weight[tables[m], tiles[m, k, n]]`` (float64 accumulation, one rounding)."""
    m, k, n = tiles.shape
    for r in range(m):
        w = weight[tables[r]]
        for c in range(k):
            s = 0.0
            for i in range(n):
                s += w[tiles[r, c, i]]
            out[r, c] = s


@_JIT
def table_add(weight: np.ndarray, tables: np.ndarray, tiles: np.ndarray, step: np.ndarray) -> None:
    """``weight[tables[m], tiles[m, n]] += step[m]`` for every n, in row order (repeated tiles add up);
    ``step`` has the weights' dtype, so each add rounds as torch's ``index_add_`` does."""
    m, n = tiles.shape
    for r in range(m):
        w = weight[tables[r]]
        s = step[r]
        for i in range(n):
            w[tiles[r, i]] += s


def compiled_tiles(coder: TileCoding, values: torch.Tensor) -> torch.Tensor:
    """``coder.tiles(values)`` [M, A, N] computed by :func:`tile_indices` (bit for bit the same)."""
    if values.shape[-1] != coder.num_features:
        raise ValueError(f"expected {coder.num_features} state variables, got shape {tuple(values.shape)}")
    x = values.detach().to(torch.float64).reshape(-1, coder.num_features).numpy()
    out = tile_indices(x, coder.widths.numpy(), coder.tilings, coder.num_actions, coder.size)
    return torch.from_numpy(out).view(*values.shape[:-1], coder.num_actions, coder.active_tiles)


def compiled_values(coder: TileCoding, tables: torch.Tensor, tiles: torch.Tensor) -> torch.Tensor:
    """``coder(tables, tiles)`` for tiles [M, K, N]: the sums [M, K] in the weights' dtype."""
    idx = tiles.to(torch.int64).contiguous().numpy()
    out = np.empty(idx.shape[:2], dtype=np.float64)
    table_sums(coder.weight.numpy(), tables.to(torch.int64).contiguous().numpy(), idx, out)
    return torch.from_numpy(out).to(coder.weight.dtype)


def compiled_add_(coder: TileCoding, tables: torch.Tensor, tiles: torch.Tensor, step: torch.Tensor) -> None:
    """``coder.add_(tables, tiles, step[:, None])``: add ``step`` [M] to each of row m's tiles [M, N]."""
    table_add(
        coder.weight.numpy(),
        tables.to(torch.int64).contiguous().numpy(),
        tiles.to(torch.int64).contiguous().numpy(),
        step.detach().to(coder.weight.dtype).contiguous().numpy(),
    )
