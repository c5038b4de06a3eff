"""Whole games of a fused policy in compiled code: the CE value R and H^ combined at every placement.

The compiled twin of :class:`~hfrl_torch.fusion.fusion.Fusion`'s decision rule over Tetris afterstates, so
that a CE population can be scored under fusion at the engine's speed (thesis Figure 4.1: CE + human
feedback). It takes the rule's code (``schemes.COMPILED_RULES``), the scale and the weights from the
``Fusion`` it is given, and counts the matches behind the trust factor as ``fusion.trust.MatchCounter``
does. At each placement, for every valid placement a: R(a) = theta . f_env(s'_a) (the CE value) and
H^(a) = h . (f_h(s'_a) - f_h(s)) (TAMER's model over feature changes). With ``scaling="decision"`` both are
rescaled to [0, 1] over the placements that can be chosen, then fused (see ``fuse_values``). Every argmax is
"the first on ties, a game-ending placement only when all end the game", the env's rule.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch
from numba import prange

from hfrl_torch.envs.tetris.engine_numba import (
    SPARE_ROWS,
    best_placement,
    board_state_features,
    check_weights,
    piece_afterstates,
    spawn_blocked,
    spawn_masks,
)
from hfrl_torch.envs.tetris.features import BT, KNOX, feature_size
from hfrl_torch.envs.tetris.pieces import placement_table
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.envs.tetris.sequence import game_key, piece_at, uniform_index
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schemes import COMPILED_RULES

ENV_ONLY = COMPILED_RULES["none"]
HUMAN_ONLY = COMPILED_RULES["human_only"]
ADDITIVE = COMPILED_RULES["linear"]
EXPONENTIAL = COMPILED_RULES["exponential"]
CONTROL_SHARING = COMPILED_RULES["control_sharing"]
COMPILED_SCALINGS = ("none", "decision")

_COIN_SALT = 0x5BD1E995
_COIN_RESOLUTION = 1 << 24


@numba.njit(cache=True, nogil=True)
def _rescale(values: np.ndarray, over: np.ndarray, n: int, any_alive: bool, out: np.ndarray) -> None:
    """``(v - min) / (max - min)`` over the placements that can be chosen (0 where all are equal)."""
    lo = np.inf
    hi = -np.inf
    for a in range(n):
        if any_alive and over[a]:
            continue
        lo = min(lo, values[a])
        hi = max(hi, values[a])
    span = hi - lo
    for a in range(n):
        out[a] = (values[a] - lo) / span if span > 0 else 0.0


@numba.njit(cache=True, nogil=True, parallel=True)
def play_fused_games(
    env_weights: np.ndarray,
    human_weights: np.ndarray,
    rule: int,
    weight: np.ndarray,
    normalise: bool,
    seeds: np.ndarray,
    width: int,
    height: int,
    fid: int,
    n_env: int,
    bag: bool,
    spawn_topout: bool,
    max_pieces: int,
    num_actions: np.ndarray,
    row_masks: np.ndarray,
    bottom: np.ndarray,
    top: np.ndarray,
    column: np.ndarray,
    piece_width: np.ndarray,
    piece_height: np.ndarray,
    spawn_mask: np.ndarray,
    out_lines: np.ndarray,
    out_pieces: np.ndarray,
    out_capped: np.ndarray,
    out_matches: np.ndarray,
    out_compared: np.ndarray,
    out_human_return: np.ndarray,
) -> None:
    """Play game g with ``env_weights[g]`` (over the first ``n_env`` features of ``fid``) fused with
    ``human_weights[g]`` (over all of ``fid``) by ``rule`` at weight ``weight[g]``.

    Also counts, for the trust factor, the placements where H^ prefers some choosable placement
    (``out_compared``) and, of those, the ones where argmax H^ = argmax R (``out_matches``), and sums H^ of
    the placements taken (``out_human_return``, raw H^, for reward shaping).
    """
    n_games = seeds.shape[0]
    nrows = height + SPARE_ROWS
    nf = human_weights.shape[1]
    max_actions = 0
    for p in range(num_actions.shape[0]):
        max_actions = max(max_actions, num_actions[p])
    for g in prange(n_games):
        rows = np.zeros(nrows, np.int64)
        hts = np.zeros(width, np.int64)
        after_rows = np.empty((max_actions, nrows), np.int64)
        after_h = np.empty((max_actions, width), np.int64)
        feat = np.empty((max_actions, nf), np.float64)
        after_lines = np.empty(max_actions, np.int64)
        now = np.empty(nf, np.float64)
        r = np.empty(max_actions, np.float64)
        hv = np.empty(max_actions, np.float64)
        rn = np.empty(max_actions, np.float64)
        hn = np.empty(max_actions, np.float64)
        score = np.empty(max_actions, np.float64)
        over = np.empty(max_actions, np.bool_)
        key = game_key(seeds[g])
        w = weight[g]
        i = 0
        lines_total = 0
        filled = 0
        matches = 0
        compared = 0
        human_return = 0.0
        capped = False
        p = piece_at(key, 0, bag)
        while True:
            if max_pieces > 0 and i >= max_pieces:
                capped = True
                break
            na = num_actions[p]
            board_state_features(rows, hts, width, height, fid, filled, now)
            piece_afterstates(
                rows,
                hts,
                filled,
                p,
                width,
                height,
                fid,
                num_actions,
                row_masks,
                bottom,
                top,
                column,
                piece_width,
                piece_height,
                after_rows,
                after_h,
                feat,
                over,
                after_lines,
            )
            any_alive = False
            for a in range(na):
                rv = 0.0
                for k in range(n_env):
                    rv += env_weights[g, k] * feat[a, k]
                h = 0.0
                for k in range(nf):
                    h += human_weights[g, k] * (feat[a, k] - now[k])
                r[a] = rv
                hv[a] = h
                any_alive = any_alive or not over[a]
            best_env = best_placement(r, over, na)
            best_human = best_placement(hv, over, na)
            h_lo = np.inf
            h_hi = -np.inf
            for a in range(na):
                if any_alive and over[a]:
                    continue
                h_lo = min(h_lo, hv[a])
                h_hi = max(h_hi, hv[a])
            if h_hi > h_lo:
                compared += 1
                if best_env == best_human:
                    matches += 1
            if rule == ENV_ONLY:
                pick = best_env
            elif rule == HUMAN_ONLY:
                pick = best_human
            elif rule == CONTROL_SHARING:
                coin = uniform_index(key ^ _COIN_SALT, i, _COIN_RESOLUTION) / _COIN_RESOLUTION
                pick = best_human if coin < min(w, 1.0) else best_env
            else:
                if normalise:
                    _rescale(r, over, na, any_alive, rn)
                    _rescale(hv, over, na, any_alive, hn)
                else:
                    for a in range(na):
                        rn[a] = r[a]
                        hn[a] = hv[a]
                for a in range(na):
                    if rule == ADDITIVE:
                        score[a] = rn[a] + w * hn[a]
                    else:
                        x = hn[a]
                        s = 0.0 if x == 0 else (abs(x) ** w) * (1.0 if x > 0 else -1.0)
                        score[a] = rn[a] * (1.0 + s)
                pick = best_placement(score, over, na)
            human_return += hv[pick]
            lines = after_lines[pick]
            end = over[pick]
            for rr in range(nrows):
                rows[rr] = after_rows[pick, rr]
            for c in range(width):
                hts[c] = after_h[pick, c]
            filled += 4 - lines * width
            lines_total += lines
            i += 1
            if end:
                break
            p = piece_at(key, i, bag)
            if spawn_topout and spawn_blocked(rows, height, width, spawn_mask, p):
                break
        out_lines[g] = lines_total
        out_pieces[g] = i
        out_capped[g] = capped
        out_matches[g] = matches
        out_compared[g] = compared
        out_human_return[g] = human_return


class FusedGames(NamedTuple):
    """Results per game of :func:`play_fused`."""

    lines: torch.Tensor  # int64 [G]
    pieces: torch.Tensor  # int64 [G]
    capped: torch.Tensor  # bool [G]: stopped by max_pieces
    matches: torch.Tensor  # int64 [G]: compared placements where argmax H^ = argmax R
    compared: torch.Tensor  # int64 [G]: placements where H^ prefers some choosable placement
    human_return: torch.Tensor  # float64 [G]: sum of H^ over the placements taken


def play_fused(
    rules: TetrisRules,
    env_features: str,
    human_features: str,
    env_weights: torch.Tensor,
    human_weights: torch.Tensor,
    fusion: Fusion,
    seeds: torch.Tensor,
    *,
    max_pieces: int = 0,
    weight: float | torch.Tensor | None = None,
) -> FusedGames:
    """Play one game per seed under ``fusion``'s decision rule; weights are [F] or [G, F].

    The weight on H^ is the fusion's (learner 0; or ``weight``, one number or one per game). The env
    features must be the human features or their prefix (``bt`` is the first 21 of ``knox``).
    """
    if fusion.scaling not in COMPILED_SCALINGS:
        raise ValueError(
            f"compiled Tetris games fuse with scaling {', '.join(COMPILED_SCALINGS)}, not {fusion.scaling!r}"
        )
    ids = {"bt": BT, "knox": KNOX}
    for what, name in (("env_features", env_features), ("human_features", human_features)):
        if name not in ids:
            raise ValueError(f"{what}={name!r} is invalid for fused play; allowed: bt, knox")
    if env_features == "knox" and human_features == "bt":
        raise ValueError(
            "env_features='knox' needs human_features='knox' (bt is a prefix of knox, not the reverse)"
        )
    fid = ids[human_features]
    g = seeds.shape[0]
    n_env = feature_size(ids[env_features], rules.width)
    n_h = feature_size(fid, rules.width)
    check_weights(env_weights, n_env, g)
    check_weights(human_weights, n_h, g)
    if weight is None:
        weight = fusion.weight()[0]
    w = torch.as_tensor(weight, dtype=torch.float64).cpu().reshape(-1).expand(g).contiguous()
    if not (torch.isfinite(w).all() and (w >= 0).all()):
        raise ValueError(f"fusion weight must be finite and >= 0, got {weight!r}")

    def rows(x: torch.Tensor, n: int) -> np.ndarray:
        x = x.detach().to(torch.float64).cpu()
        return (x.expand(g, n) if x.dim() == 1 else x).contiguous().numpy()

    table = placement_table(rules.width)
    out = (
        np.zeros(g, np.int64),
        np.zeros(g, np.int64),
        np.zeros(g, np.bool_),
        np.zeros(g, np.int64),
        np.zeros(g, np.int64),
        np.zeros(g, np.float64),
    )
    play_fused_games(
        rows(env_weights, n_env),
        rows(human_weights, n_h),
        fusion.compiled_rule,
        w.numpy(),
        fusion.scaling == "decision",
        seeds.cpu().numpy().astype(np.int64),
        rules.width,
        rules.height,
        fid,
        n_env,
        rules.bag,
        rules.spawn_topout,
        max_pieces,
        table.num_actions,
        table.row_masks,
        table.bottom,
        table.top,
        table.column,
        table.piece_width,
        table.piece_height,
        spawn_masks(table),
        *out,
    )
    return FusedGames(*(torch.from_numpy(o) for o in out))
