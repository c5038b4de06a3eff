"""Dellacherie's hand-weighted evaluation of every placement, from the env's observation alone.

The simulated trainers judge the agent's placements with a strong reference: Dellacherie's weights over
the Dellacherie features (``features.DELLACHERIE_WEIGHTS``). The env computes one feature set only, so the
boards are rebuilt here from the ``board`` and ``piece`` observations and evaluated by one compiled kernel
that reuses the numba engine's placement and feature code. Working from observations keeps the trainers
independent of the env's engine (numba or torch).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.envs.tetris.engine_numba import (
    SPARE_ROWS,
    best_placement,
    board_state_features,
    filled_cells,
    piece_afterstates,
)
from hfrl_torch.envs.tetris.features import DELLACHERIE, DELLACHERIE_WEIGHTS
from hfrl_torch.envs.tetris.pieces import placement_table


@numba.njit(cache=True, nogil=True)
def _evaluate(
    rows: np.ndarray,
    heights: np.ndarray,
    pieces: np.ndarray,
    active: np.ndarray,
    width: int,
    height: int,
    weights: np.ndarray,
    num_actions: np.ndarray,
    row_masks: np.ndarray,
    bottom: np.ndarray,
    top: np.ndarray,
    column: np.ndarray,
    piece_width: np.ndarray,
    piece_height: np.ndarray,
    out_value: np.ndarray,
    out_board_value: np.ndarray,
    out_terminal: np.ndarray,
    out_best: np.ndarray,
    out_same: np.ndarray,
    out_before: np.ndarray,
) -> None:
    """Per board: every placement's full and board-only value, the best one, and which give its board."""
    nb = rows.shape[0]
    nrows = height + SPARE_ROWS
    a_max = num_actions.max()
    after_rows = np.empty((a_max, nrows), np.int64)  # every placement's afterstate
    after_h = np.empty((a_max, width), np.int64)
    after_lines = np.empty(a_max, np.int64)
    feat = np.empty((a_max, 6), np.float64)
    for b in range(nb):
        out_value[b, :] = 0.0
        out_board_value[b, :] = 0.0
        out_terminal[b, :] = False
        out_same[b, :] = False
        out_best[b] = -1
        out_before[b] = 0.0
        if not active[b]:
            continue
        filled = filled_cells(rows[b], nrows)
        board_state_features(rows[b], heights[b], width, height, DELLACHERIE, filled, feat[0])
        for k in range(2, 6):
            out_before[b] += weights[k] * feat[0, k]
        n = piece_afterstates(
            rows[b],
            heights[b],
            filled,
            pieces[b],
            width,
            height,
            DELLACHERIE,
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
            out_terminal[b],
            after_lines,
        )
        for a in range(n):
            board_v = 0.0
            for k in range(2, 6):
                board_v += weights[k] * feat[a, k]
            out_value[b, a] = board_v + weights[0] * feat[a, 0] + weights[1] * feat[a, 1]
            out_board_value[b, a] = board_v
        # the engines' rule: game-ending placements only when every placement ends the game
        out_best[b] = best_placement(out_value[b], out_terminal[b], n)
        best = after_rows[out_best[b]]
        for a in range(n):
            same = True
            for r in range(nrows):
                if after_rows[a, r] != best[r]:
                    same = False
                    break
            out_same[b, a] = same


@dataclass(frozen=True)
class ReferenceEvaluation:
    """Dellacherie's evaluation of every placement of B boards (A = the placement table's width).

    :param value: ``[B, A]`` w . f(afterstate) over all six features (the reference policy's score).
    :param board_value: ``[B, A]`` the same without landing height and eroded cells (the board alone).
    :param board_value_before: ``[B]`` the board-only value of the board before the placement.
    :param terminal: ``[B, A]`` the placement ends the game.
    :param best: ``[B]`` the reference policy's placement: highest value, the first on ties, a game-ending
        one only when all are (-1 on inactive boards).
    :param same_as_best: ``[B, A]`` the placement leaves the same board as ``best`` (lines cleared included).
    """

    value: torch.Tensor
    board_value: torch.Tensor
    board_value_before: torch.Tensor
    terminal: torch.Tensor
    best: torch.Tensor
    same_as_best: torch.Tensor


def boards_to_bitmasks(board: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The numba engine's representation (row bitmasks ``[B, H + 4]``, column heights ``[B, W]``) of
    ``board`` cells ``[B, H, W]`` (row 0 at the bottom)."""
    b, h, w = board.shape
    cells = board.to(torch.int64).cpu()
    bits = (cells << torch.arange(w, dtype=torch.int64)).sum(-1)
    rows = torch.zeros(b, h + SPARE_ROWS, dtype=torch.int64)
    rows[:, :h] = bits
    levels = torch.arange(1, h + 1, dtype=torch.int64).view(1, h, 1)
    heights = (cells * levels).amax(dim=1)
    return rows.numpy(), heights.contiguous().numpy()


def evaluate_placements(
    obs: TensorDictBase, active: torch.Tensor | None = None, weights: tuple[float, ...] = DELLACHERIE_WEIGHTS
) -> ReferenceEvaluation:
    """Evaluate every placement of the current piece on each board of a TetrisEnv observation."""
    board = obs[keys.BOARD]
    b, h, w = board.shape
    rows, heights = boards_to_bitmasks(board)
    pieces = obs[keys.PIECE].reshape(b).to(torch.int64).cpu().numpy()
    act = np.ones(b, np.bool_) if active is None else active.reshape(b).cpu().numpy().astype(np.bool_)
    t = placement_table(w)
    a_max = t.max_actions
    value = np.zeros((b, a_max), np.float64)
    board_value = np.zeros((b, a_max), np.float64)
    terminal = np.zeros((b, a_max), np.bool_)
    best = np.zeros(b, np.int64)
    same = np.zeros((b, a_max), np.bool_)
    before = np.zeros(b, np.float64)
    _evaluate(
        rows,
        heights,
        pieces,
        act,
        w,
        h,
        np.asarray(weights, np.float64),
        t.num_actions,
        t.row_masks,
        t.bottom,
        t.top,
        t.column,
        t.piece_width,
        t.piece_height,
        value,
        board_value,
        terminal,
        best,
        same,
        before,
    )
    return ReferenceEvaluation(
        value=torch.from_numpy(value),
        board_value=torch.from_numpy(board_value),
        board_value_before=torch.from_numpy(before),
        terminal=torch.from_numpy(terminal),
        best=torch.from_numpy(best),
        same_as_best=torch.from_numpy(same),
    )
