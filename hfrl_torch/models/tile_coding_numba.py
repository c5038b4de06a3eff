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
_INLINE = numba.njit(cache=True, nogil=True, inline="always")


# unsigned copies for the multiply-add rounds: operands below 2^31, so LLVM multiplies 32 x 32 -> 64 bits
# and vectorises the loop over tilings
_P = np.uint64(_PRIME)
_M1, _A1, _M2, _A2 = np.uint64(_MUL1), np.uint64(_ADD1), np.uint64(_MUL2), np.uint64(_ADD2)
_S31, _S15 = np.uint64(31), np.uint64(15)


@_INLINE
def _mod_prime(x: np.int64) -> np.int64:
    """``x mod (2^31 - 1)`` in [0, 2^31 - 1) for any int64 (Python's ``%``, as ``torch.remainder``), without
    a division or a branch: 2^31 = 1 modulo the Mersenne prime, so folding the high bits onto the low ones
    keeps the residue."""
    s = (x >> 31) + (x & _PRIME)  # arithmetic shift: the floor, negative x included
    s = (s >> 31) + (s & _PRIME)  # now in [-2, 2^31 + 1]
    s += _PRIME & (s >> 63)  # negative: add the prime
    return s - (_PRIME & ((_PRIME - 1 - s) >> 63))  # >= the prime: subtract it


@_INLINE
def _mod_prime_unsigned(x: np.uint64) -> np.uint64:
    """``x mod (2^31 - 1)`` for x < 2^63 (a product of two residues plus a constant)."""
    s = (x >> _S31) + (x & _P)
    s = (s >> _S31) + (s & _P)
    return s - _P if s >= _P else s


@_JIT
def tile_row(
    values: np.ndarray, widths: np.ndarray, tilings: int, num_actions: int, size: int, out: np.ndarray
) -> None:
    """Active tiles ``out`` [A, F * T] of one state ``values`` [F]: ``hash_tiles(tile_coordinates)`` of
    ``tile_coding``, the same float64 coordinates and int64 hash (keys wrap as torch's int64 do)."""
    f = widths.shape[0]
    span = num_actions * f * tilings
    low_bits = np.uint64(size - 1)
    power_of_two = size & (size - 1) == 0
    keys = np.empty(tilings, dtype=np.int64)
    for v in range(f):
        q = np.int64(math.floor((np.float64(values[v]) / widths[v]) * tilings))
        base = q // tilings
        rest = q - base * tilings  # tiling j's coordinate: base while j <= rest, base - 1 after
        for j in range(tilings):
            keys[j] = (base - np.int64(j > rest)) * span + v * tilings + j
        for a in range(num_actions):
            group = np.int64(a * f * tilings)
            row = out[a, v * tilings : (v + 1) * tilings]
            for j in range(tilings):
                h = np.uint64(_mod_prime(keys[j] + group))
                h = _mod_prime_unsigned(h * _M1 + _A1)
                h = h ^ (h >> _S15)
                h = _mod_prime_unsigned(h * _M2 + _A2)
                row[j] = np.int64(h & low_bits) if power_of_two else np.int64(h) % size


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


@_INLINE
def tile_sum(w: np.ndarray, tiles: np.ndarray) -> float:
    """``sum_n w[tiles[n]]`` of one table ``w`` over one action's ``tiles`` [N] (float64 accumulation)."""
    s = 0.0
    for i in range(tiles.shape[0]):
        s += w[tiles[i]]
    return s


@_JIT
def table_sums(weight: np.ndarray, tables: np.ndarray, tiles: np.ndarray, out: np.ndarray) -> None:
    """``out[m, k] = sum_n weight[tables[m], tiles[m, k, n]]`` (float64 accumulation, one rounding)."""
    m, k, _ = tiles.shape
    for r in range(m):
        w = weight[tables[r]]
        for c in range(k):
            out[r, c] = tile_sum(w, tiles[r, c])


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
