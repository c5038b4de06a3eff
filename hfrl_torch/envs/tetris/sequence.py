"""Counter-based piece sequences: piece i of a game is a pure function of (seed, i).

Both engines (numba and torch) compute the same 32-bit integer hash, so a game
played from a seed has the same pieces on every path and every device, and
candidates of the cross-entropy method can be compared on common random numbers.
"""

from __future__ import annotations

import numba
import torch

MASK32 = 0xFFFFFFFF
_C1 = 0x7FEB352D
_C2 = 0x846CA68B
_GOLDEN = 0x9E3779B9
_BAG_SALT = 0x85EBCA6B
_POLICY_SALT = 0xC2B2AE35


@numba.njit(cache=True, inline="always")
def _mulmod32(x: int, c: int) -> int:
    # x * c mod 2^32 without overflowing int64: split c into 16-bit halves
    return (x * (c & 0xFFFF) + (((x * (c >> 16)) & 0xFFFF) << 16)) & MASK32


@numba.njit(cache=True, nogil=True)
def mix32(x: int) -> int:
    """lowbias32 integer hash (Wellons) on the low 32 bits of x."""
    x &= MASK32
    x ^= x >> 16
    x = _mulmod32(x, _C1)
    x ^= x >> 15
    x = _mulmod32(x, _C2)
    x ^= x >> 16
    return x


@numba.njit(cache=True, nogil=True)
def game_key(seed: int) -> int:
    """32-bit key of a game from its 63-bit seed."""
    k0 = mix32((seed & MASK32) ^ _GOLDEN)
    return mix32(k0 ^ ((seed >> 32) & MASK32))


@numba.njit(cache=True, nogil=True)
def piece_at(key: int, index: int, bag: bool) -> int:
    """Piece number (0..6, order I O T S Z L J) of the ``index``-th piece of the game ``key``."""
    if not bag:
        h = mix32(key ^ mix32(index))
        return (h * 7) >> 32
    j = index // 7
    perm0, perm1, perm2, perm3, perm4, perm5, perm6 = 0, 1, 2, 3, 4, 5, 6
    perm = [perm0, perm1, perm2, perm3, perm4, perm5, perm6]
    for k in range(6, 0, -1):
        r = (mix32(key ^ mix32(((j * 8 + k) & MASK32) ^ _BAG_SALT)) * (k + 1)) >> 32
        perm[k], perm[r] = perm[r], perm[k]
    return perm[index % 7]


@numba.njit(cache=True, nogil=True)
def uniform_index(key: int, index: int, n: int) -> int:
    """A uniform draw in [0, n) for step ``index`` of the random stream ``key`` (random policy)."""
    h = mix32(key ^ mix32(index ^ _POLICY_SALT))
    return (h * n) >> 32


# ---- torch versions of the same functions (elementwise over int64 tensors) ----


def _mulmod32_t(x: torch.Tensor, c: int) -> torch.Tensor:
    return (x * (c & 0xFFFF) + (((x * (c >> 16)) & 0xFFFF) << 16)) & MASK32


def mix32_t(x: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`mix32` on int64 tensors."""
    x = x & MASK32
    x = x ^ (x >> 16)
    x = _mulmod32_t(x, _C1)
    x = x ^ (x >> 15)
    x = _mulmod32_t(x, _C2)
    return x ^ (x >> 16)


def game_key_t(seed: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`game_key`."""
    k0 = mix32_t((seed & MASK32) ^ _GOLDEN)
    return mix32_t(k0 ^ ((seed >> 32) & MASK32))


def piece_at_t(key: torch.Tensor, index: torch.Tensor, bag: bool) -> torch.Tensor:
    """Torch twin of :func:`piece_at`, elementwise over keys and indices."""
    if not bag:
        return (mix32_t(key ^ mix32_t(index)) * 7) >> 32
    j = index // 7
    perm = torch.arange(7, device=key.device).expand(*key.shape, 7).clone()
    for k in range(6, 0, -1):
        r = (mix32_t(key ^ mix32_t(((j * 8 + k) & MASK32) ^ _BAG_SALT)) * (k + 1)) >> 32
        pk = perm[..., k].clone()
        pr = perm.gather(-1, r.unsqueeze(-1)).squeeze(-1)
        perm[..., k] = pr
        perm.scatter_(-1, r.unsqueeze(-1), pk.unsqueeze(-1))
    return perm.gather(-1, (index % 7).unsqueeze(-1)).squeeze(-1)


def uniform_index_t(key: torch.Tensor, index: torch.Tensor, n: torch.Tensor) -> torch.Tensor:
    """Torch twin of :func:`uniform_index`."""
    return (mix32_t(key ^ mix32_t(index ^ _POLICY_SALT)) * n) >> 32
