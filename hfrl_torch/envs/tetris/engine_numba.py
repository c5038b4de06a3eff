"""Compiled bitboard Tetris engine (numba), the CPU fast path.

A board is ``H + 4`` int64 row bitmasks (bit c = column c; the 4 spare rows hold a
piece that sticks out above the top before its lines clear) plus the column
heights. Rules are the "simplified" rules of the RL literature: a placement drops
a piece straight down, full rows are removed, and the game is over when a cell is
still above row H afterwards (optionally also when the next piece cannot spawn).

The kernels work over whole batches: afterstate features of every placement of
every board, one placement per board, and whole games played by linear policies
(the cross-entropy method's inner loop) with ``prange`` over games. They, the compiled
fused games (``fusion.compiled``) and the reference trainer's evaluation
(``trainers.reference_policy``) all place a piece through :func:`piece_afterstates` (every
placement of one piece on one board: afterstates, features, game ends, lines) and choose
through :func:`best_placement`.
"""

from __future__ import annotations

import numba
import numpy as np
import torch
from numba import prange

from hfrl_torch.envs.tetris.features import BT, DT, KNOX, feature_size
from hfrl_torch.envs.tetris.pieces import PlacementTable, placement_table
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.envs.tetris.sequence import game_key, piece_at, uniform_index

SPARE_ROWS = 4

POLICY_LINEAR = 0
POLICY_RANDOM = 1


@numba.njit(cache=True, inline="always")
def _popcount(x: int) -> int:
    x = x - ((x >> 1) & 0x5555555555555555)
    x = (x & 0x3333333333333333) + ((x >> 2) & 0x3333333333333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F0F0F0F0F
    return ((x * 0x0101010101010101) >> 56) & 0xFF


@numba.njit(cache=True, nogil=True)
def _place(
    rows: np.ndarray,
    heights: np.ndarray,
    out_rows: np.ndarray,
    out_heights: np.ndarray,
    width: int,
    height: int,
    row_masks: np.ndarray,
    bottom: np.ndarray,
    top: np.ndarray,
    col: int,
    pw: int,
    ph: int,
) -> tuple[int, int, int, bool]:
    """Drop one placement onto (rows, heights) into (out_rows, out_heights).

    Returns (lines cleared, landing row of the piece's bottom, piece cells removed, game over).
    """
    land = 0
    for c in range(pw):
        y = heights[col + c] - bottom[c]
        if y > land:
            land = y
    nrows = height + SPARE_ROWS
    for r in range(nrows):
        out_rows[r] = rows[r]
    for c in range(width):
        out_heights[c] = heights[c]
    full = (1 << width) - 1
    lines = 0
    removed_piece_cells = 0
    removed = 0  # bitmask over piece rows 0..3 that are full
    for k in range(ph):
        out_rows[land + k] |= row_masks[k]
        if out_rows[land + k] == full:
            lines += 1
            removed |= 1 << k
            removed_piece_cells += _popcount(row_masks[k])
    for c in range(pw):
        out_heights[col + c] = land + top[c]
    if lines > 0:
        # compact rows: keep the rows that are not full
        dst = land
        for r in range(land, nrows):
            k = r - land
            if k < ph and (removed >> k) & 1:
                continue
            out_rows[dst] = out_rows[r]
            dst += 1
        for r in range(dst, nrows):
            out_rows[r] = 0
        for c in range(width):
            bit = 1 << c
            r = out_heights[c] - lines
            while r >= 0 and (out_rows[r] & bit) == 0:
                r -= 1
            out_heights[c] = r + 1
    over = False
    for c in range(width):
        if out_heights[c] > height:
            over = True
    return lines, land, removed_piece_cells, over


@numba.njit(cache=True, nogil=True)
def spawn_blocked(rows: np.ndarray, height: int, width: int, spawn_masks: np.ndarray, piece: int) -> bool:
    """True if the piece in its spawn orientation at the top centre overlaps the stack."""
    ph = 0
    for k in range(4):
        if spawn_masks[piece, k] != 0:
            ph = k + 1
    for k in range(ph):
        if rows[height - ph + k] & spawn_masks[piece, k]:
            return True
    return False


@numba.njit(cache=True, nogil=True)
def _features(
    rows: np.ndarray,
    heights: np.ndarray,
    width: int,
    height: int,
    fid: int,
    filled: int,
    landing_height: float,
    eroded: int,
    out: np.ndarray,
) -> None:
    """Write feature set ``fid`` of a board into ``out`` (``filled`` = number of filled cells)."""
    if fid == BT or fid == KNOX:
        hsum = 0
        hmax = 0
        for c in range(width):
            h = heights[c]
            out[c] = h
            hsum += h
            if h > hmax:
                hmax = h
        for c in range(width - 1):
            d = heights[c] - heights[c + 1]
            out[width + c] = d if d >= 0 else -d
        out[2 * width - 1] = hmax
        out[2 * width] = hsum - filled
        if fid == KNOX:
            wmax = 0
            wsum = 0
            for c in range(width):
                left = heights[c - 1] if c > 0 else height
                right = heights[c + 1] if c < width - 1 else height
                m = left if left < right else right
                d = m - heights[c]
                if d > 0:
                    wsum += d
                    if d > wmax:
                        wmax = d
            n = 2 * width + 1
            out[n] = wmax
            out[n + 1] = wsum
            for i in range(n + 2):
                out[n + 2 + i] = out[i] * out[i] / 100.0
        return
    # Dellacherie and Dellacherie-Thiery
    full = (1 << width) - 1
    walls = 1 | (1 << (width + 1))
    row_tr = 0
    col_tr = 0
    prev = full
    for r in range(height):
        x = (rows[r] << 1) | walls
        row_tr += _popcount((x ^ (x >> 1)) & ((1 << (width + 1)) - 1))
        col_tr += _popcount(rows[r] ^ prev)
        prev = rows[r]
    hsum = 0
    for c in range(width):
        hsum += heights[c]
    holes = hsum - filled
    wells = 0
    for c in range(width):
        bit = 1 << c
        for r in range(height - 1, -1, -1):
            row = rows[r]
            if row & bit:
                continue
            left = True if c == 0 else (row >> (c - 1)) & 1 == 1
            right = True if c == width - 1 else (row >> (c + 1)) & 1 == 1
            if left and right:
                wells += 1
                k = r - 1
                while k >= 0 and (rows[k] & bit) == 0:
                    wells += 1
                    k -= 1
    out[0] = landing_height
    out[1] = eroded
    out[2] = row_tr
    out[3] = col_tr
    out[4] = holes
    out[5] = wells
    if fid == DT:
        hole_depth = 0
        rows_with_holes = 0
        above = 0
        for r in range(height + SPARE_ROWS - 1, -1, -1):
            if (~rows[r]) & above & full:
                rows_with_holes += 1
            above |= rows[r]
        for c in range(width):
            bit = 1 << c
            run = 0
            for r in range(heights[c] - 1, -1, -1):
                if rows[r] & bit:
                    run += 1
                else:
                    hole_depth += run
                    run = 0
        seen = 0
        for c in range(width - 1):
            d = heights[c + 1] - heights[c]
            if -2 <= d <= 2:
                seen |= 1 << (d + 2)
        out[6] = hole_depth
        out[7] = rows_with_holes
        out[8] = _popcount(seen)


@numba.njit(cache=True, nogil=True)
def filled_cells(rows: np.ndarray, nrows: int) -> int:
    """Filled cells of a board (``nrows`` row bitmasks)."""
    n = 0
    for r in range(nrows):
        n += _popcount(rows[r])
    return n


@numba.njit(cache=True, nogil=True)
def board_state_features(
    rows: np.ndarray, heights: np.ndarray, width: int, height: int, fid: int, filled: int, out: np.ndarray
) -> None:
    """Feature set ``fid`` of one board itself (``filled`` cells; landing height and eroded cells are 0)."""
    _features(rows, heights, width, height, fid, filled, 0.0, 0, out)


@numba.njit(cache=True, inline="always")
def piece_afterstates(
    rows: np.ndarray,
    heights: np.ndarray,
    filled: int,
    piece: int,
    width: int,
    height: int,
    fid: int,
    num_actions: np.ndarray,
    row_masks: np.ndarray,
    bottom: np.ndarray,
    top: np.ndarray,
    column: np.ndarray,
    piece_width: np.ndarray,
    piece_height: np.ndarray,
    out_rows: np.ndarray,
    out_heights: np.ndarray,
    out_features: np.ndarray,
    out_over: np.ndarray,
    out_lines: np.ndarray,
) -> int:
    """Every placement of ``piece`` on one board (``rows``, ``heights``, ``filled`` cells): returns the
    number of placements n and writes, for a < n, placement a's afterstate (``out_rows[a]``,
    ``out_heights[a]``), its feature set ``fid`` (``out_features[a]``), whether it ends the game
    (``out_over[a]``) and the lines it clears (``out_lines[a]``). The tables are the placement table's."""
    p = piece
    n = num_actions[p]
    for a in range(n):
        lines, land, eroded_cells, over = _place(
            rows,
            heights,
            out_rows[a],
            out_heights[a],
            width,
            height,
            row_masks[p, a],
            bottom[p, a],
            top[p, a],
            column[p, a],
            piece_width[p, a],
            piece_height[p, a],
        )
        lh = land + 1 + (piece_height[p, a] - 1) / 2.0
        _features(
            out_rows[a],
            out_heights[a],
            width,
            height,
            fid,
            filled + 4 - lines * width,
            lh,
            lines * eroded_cells,
            out_features[a],
        )
        out_over[a] = over
        out_lines[a] = lines
    return n


@numba.njit(cache=True, nogil=True)
def best_placement(values: np.ndarray, over: np.ndarray, n: int) -> int:
    """The engines' choice among placements 0..n-1: the highest value, the first on ties, and a
    game-ending placement only when every placement ends the game (then the best of them)."""
    best = 0
    for a in range(1, n):
        if (over[best] and not over[a]) or (over[a] == over[best] and values[a] > values[best]):
            best = a
    return best


@numba.njit(cache=True, nogil=True, parallel=True)
def afterstates_batch(
    rows: np.ndarray,
    heights: np.ndarray,
    pieces: np.ndarray,
    alive: np.ndarray,
    width: int,
    height: int,
    fid: int,
    num_actions: np.ndarray,
    row_masks: np.ndarray,
    bottom: np.ndarray,
    top: np.ndarray,
    column: np.ndarray,
    piece_width: np.ndarray,
    piece_height: np.ndarray,
    out_features: np.ndarray,
    out_mask: np.ndarray,
    out_terminal: np.ndarray,
    out_lines: np.ndarray,
) -> None:
    """Features of every placement's afterstate for a batch of boards ([B, A, F] etc.)."""
    nb = rows.shape[0]
    nrows = height + SPARE_ROWS
    a_max = out_mask.shape[1]
    for b in prange(nb):
        after_rows = np.empty((a_max, nrows), np.int64)
        after_h = np.empty((a_max, width), np.int64)
        out_features[b, :, :] = 0.0
        out_mask[b, :] = False
        out_terminal[b, :] = False
        out_lines[b, :] = 0
        if not alive[b]:
            continue
        n = piece_afterstates(
            rows[b],
            heights[b],
            filled_cells(rows[b], nrows),
            pieces[b],
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
            out_features[b],
            out_terminal[b],
            out_lines[b],
        )
        out_mask[b, :n] = True


@numba.njit(cache=True, nogil=True)
def board_features(
    rows: np.ndarray, heights: np.ndarray, width: int, height: int, fid: int, out: np.ndarray
) -> None:
    """Features of the boards themselves (no placement: landing height and eroded cells are 0)."""
    nrows = height + SPARE_ROWS
    for b in range(rows.shape[0]):
        board_state_features(rows[b], heights[b], width, height, fid, filled_cells(rows[b], nrows), out[b])


@numba.njit(cache=True, nogil=True)
def step_batch(
    rows: np.ndarray,
    heights: np.ndarray,
    pieces: np.ndarray,
    keys: np.ndarray,
    index: np.ndarray,
    alive: np.ndarray,
    actions: np.ndarray,
    width: int,
    height: int,
    bag: bool,
    spawn_topout: bool,
    num_actions: np.ndarray,
    row_masks: np.ndarray,
    bottom: np.ndarray,
    top: np.ndarray,
    column: np.ndarray,
    piece_width: np.ndarray,
    piece_height: np.ndarray,
    spawn_masks: np.ndarray,
    out_lines: np.ndarray,
) -> None:
    """Apply one placement per live board in place; boards that end their game get alive = False."""
    nrows = height + SPARE_ROWS
    tmp_rows = np.empty(nrows, np.int64)
    tmp_h = np.empty(width, np.int64)
    for b in range(rows.shape[0]):
        out_lines[b] = 0
        if not alive[b]:
            continue
        p = pieces[b]
        a = actions[b]
        lines, _, _, over = _place(
            rows[b],
            heights[b],
            tmp_rows,
            tmp_h,
            width,
            height,
            row_masks[p, a],
            bottom[p, a],
            top[p, a],
            column[p, a],
            piece_width[p, a],
            piece_height[p, a],
        )
        rows[b, :] = tmp_rows
        heights[b, :] = tmp_h
        out_lines[b] = lines
        index[b] += 1
        pieces[b] = piece_at(keys[b], index[b], bag)
        if over or (spawn_topout and spawn_blocked(tmp_rows, height, width, spawn_masks, pieces[b])):
            alive[b] = False


@numba.njit(cache=True, nogil=True, parallel=True)
def play_games(
    weights: np.ndarray,
    seeds: np.ndarray,
    policy: int,
    policy_seeds: np.ndarray,
    width: int,
    height: int,
    fid: int,
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
    spawn_masks: np.ndarray,
    out_lines: np.ndarray,
    out_pieces: np.ndarray,
    out_capped: np.ndarray,
) -> None:
    """Play whole games, game g with linear weights ``weights[g]`` (or uniformly random moves).

    A linear policy takes the placement of highest ``w . f(afterstate)``, the first on ties,
    and a game-ending placement only when every placement ends the game (then the best of them).
    ``max_pieces`` <= 0 plays to the end; otherwise a game stops (``out_capped``) after that many pieces.
    """
    n_games = seeds.shape[0]
    nrows = height + SPARE_ROWS
    nf = weights.shape[1]
    a_max = 0
    for q in range(num_actions.shape[0]):
        a_max = max(a_max, num_actions[q])
    for g in prange(n_games):
        rows = np.zeros(nrows, np.int64)
        hts = np.zeros(width, np.int64)
        after_rows = np.empty((a_max, nrows), np.int64)
        after_h = np.empty((a_max, width), np.int64)
        feat = np.empty((a_max, nf), np.float64)
        after_over = np.empty(a_max, np.bool_)
        after_lines = np.empty(a_max, np.int64)
        values = np.empty(a_max, np.float64)
        key = game_key(seeds[g])
        pkey = game_key(policy_seeds[g])
        i = 0
        lines_total = 0
        filled = 0
        capped = False
        p = piece_at(key, 0, bag)
        while True:
            if max_pieces > 0 and i >= max_pieces:
                capped = True
                break
            na = num_actions[p]
            if policy == POLICY_RANDOM:
                a = uniform_index(pkey, i, na)
                best = 0
                lines, _, _, over = _place(
                    rows,
                    hts,
                    after_rows[0],
                    after_h[0],
                    width,
                    height,
                    row_masks[p, a],
                    bottom[p, a],
                    top[p, a],
                    column[p, a],
                    piece_width[p, a],
                    piece_height[p, a],
                )
                after_lines[0] = lines
                after_over[0] = over
            else:
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
                    after_over,
                    after_lines,
                )
                for a in range(na):
                    v = 0.0
                    for k in range(nf):
                        v += weights[g, k] * feat[a, k]
                    values[a] = v
                best = best_placement(values, after_over, na)
            best_lines = after_lines[best]
            best_over = after_over[best]
            for r in range(nrows):
                rows[r] = after_rows[best, r]
            for c in range(width):
                hts[c] = after_h[best, c]
            filled += 4 - best_lines * width
            lines_total += best_lines
            i += 1
            if best_over:
                break
            p = piece_at(key, i, bag)
            if spawn_topout and spawn_blocked(rows, height, width, spawn_masks, p):
                break
        out_lines[g] = lines_total
        out_pieces[g] = i
        out_capped[g] = capped


def spawn_masks(table: PlacementTable) -> np.ndarray:
    """[7, 4] row masks of each piece in its spawn orientation, centred on the board.

    Orientation 0's placements come first, one per column, so the centred one has
    index ``(width - piece width) // 2``.
    """
    out = np.zeros((7, 4), np.int64)
    for p in range(7):
        out[p] = table.row_masks[p, (table.width - table.piece_width[p, 0]) // 2]
    return out


@numba.njit(cache=True, nogil=True)
def reset_batch(
    mask: np.ndarray,
    seeds: np.ndarray,
    bag: bool,
    rows: np.ndarray,
    heights: np.ndarray,
    index: np.ndarray,
    alive: np.ndarray,
    keys: np.ndarray,
    pieces: np.ndarray,
) -> None:
    """Empty the boards where ``mask`` is set and start game b from ``seeds[b]``."""
    for b in range(mask.shape[0]):
        if mask[b]:
            rows[b, :] = 0
            heights[b, :] = 0
            index[b] = 0
            alive[b] = True
            keys[b] = game_key(seeds[b])
            pieces[b] = piece_at(keys[b], 0, bag)


@numba.njit(cache=True, nogil=True)
def pieces_at(keys: np.ndarray, index: np.ndarray, bag: bool, out: np.ndarray) -> None:
    """``out[b]`` = piece ``index[b]`` of game ``keys[b]``."""
    for b in range(keys.shape[0]):
        out[b] = piece_at(keys[b], index[b], bag)


class NumbaEngine:
    """A batch of ``batch`` Tetris boards stepped by the compiled kernels (CPU only).

    State lives in numpy arrays; the torch views returned share their memory.
    """

    def __init__(self, rules: TetrisRules, batch: int, feature_id: int) -> None:
        self.rules = rules
        self.batch = batch
        self.fid = feature_id
        self.device = torch.device("cpu")
        self.table = placement_table(rules.width)
        self.spawn = spawn_masks(self.table)
        self.num_features = feature_size(feature_id, rules.width)
        nrows = rules.height + SPARE_ROWS
        self.rows = np.zeros((batch, nrows), np.int64)
        self.heights = np.zeros((batch, rules.width), np.int64)
        self.pieces = np.zeros(batch, np.int64)
        self.keys = np.zeros(batch, np.int64)
        self.index = np.zeros(batch, np.int64)
        self.alive = np.zeros(batch, np.bool_)
        a_max = self.table.max_actions
        self._feat = np.zeros((batch, a_max, self.num_features), np.float32)
        self._mask = np.zeros((batch, a_max), np.bool_)
        self._term = np.zeros((batch, a_max), np.bool_)
        self._alines = np.zeros((batch, a_max), np.int64)
        self._lines = np.zeros(batch, np.int64)

    def _tables(self) -> tuple[np.ndarray, ...]:
        t = self.table
        return t.num_actions, t.row_masks, t.bottom, t.top, t.column, t.piece_width, t.piece_height

    def reset(self, mask: torch.Tensor, seeds: torch.Tensor) -> None:
        """Start new games on the boards where ``mask`` is set, game b from ``seeds[b]``."""
        reset_batch(
            mask.numpy(),
            seeds.numpy().astype(np.int64, copy=False),
            self.rules.bag,
            self.rows,
            self.heights,
            self.index,
            self.alive,
            self.keys,
            self.pieces,
        )

    def afterstates(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(features [B,A,F] float32, valid mask [B,A], game-ending [B,A], lines cleared [B,A])."""
        afterstates_batch(
            self.rows,
            self.heights,
            self.pieces,
            self.alive,
            self.rules.width,
            self.rules.height,
            self.fid,
            *self._tables(),
            self._feat,
            self._mask,
            self._term,
            self._alines,
        )
        return (
            torch.from_numpy(self._feat),
            torch.from_numpy(self._mask),
            torch.from_numpy(self._term),
            torch.from_numpy(self._alines),
        )

    def board_features(self) -> torch.Tensor:
        """Features [B, F] of the current boards."""
        out = np.zeros((self.batch, self.num_features), np.float32)
        board_features(self.rows, self.heights, self.rules.width, self.rules.height, self.fid, out)
        return torch.from_numpy(out)

    def step(self, actions: torch.Tensor) -> torch.Tensor:
        """Place the current piece of every live board; returns lines cleared [B]."""
        step_batch(
            self.rows,
            self.heights,
            self.pieces,
            self.keys,
            self.index,
            self.alive,
            actions.numpy().astype(np.int64, copy=False),
            self.rules.width,
            self.rules.height,
            self.rules.bag,
            self.rules.spawn_topout,
            *self._tables(),
            self.spawn,
            self._lines,
        )
        return torch.from_numpy(self._lines.copy())

    def boards(self) -> torch.Tensor:
        """Cells [B, H, W] as bool, row 0 at the bottom."""
        bits = 1 << np.arange(self.rules.width, dtype=np.int64)
        cells = (self.rows[:, : self.rules.height, None] & bits) != 0
        return torch.from_numpy(cells)

    def next_pieces(self) -> torch.Tensor:
        """The piece after the current one [B] (for the preview option)."""
        out = np.empty(self.batch, np.int64)
        pieces_at(self.keys, self.index + 1, self.rules.bag, out)
        return torch.from_numpy(out)

    def state_tensors(self) -> dict[str, torch.Tensor]:
        """The whole engine state as tensors (for checkpoints and for comparing engines)."""
        return {
            "rows": torch.from_numpy(self.rows.copy()),
            "heights": torch.from_numpy(self.heights.copy()),
            "pieces": torch.from_numpy(self.pieces.copy()),
            "keys": torch.from_numpy(self.keys.copy()),
            "index": torch.from_numpy(self.index.copy()),
            "alive": torch.from_numpy(self.alive.copy()),
        }


def check_weights(weights: torch.Tensor, num_features: int, games: int) -> None:
    """Raise ValueError unless ``weights`` is [F] or [games, F] with F = ``num_features``."""
    ok = (weights.dim() == 1 and weights.shape[0] == num_features) or (
        weights.dim() == 2 and tuple(weights.shape) == (games, num_features)
    )
    if not ok:
        raise ValueError(
            f"weights of shape {tuple(weights.shape)} do not fit this feature set; "
            f"allowed: [{num_features}] or [{games}, {num_features}]"
        )


def play(
    rules: TetrisRules,
    feature_id: int,
    weights: torch.Tensor,
    seeds: torch.Tensor,
    *,
    random_policy: bool = False,
    policy_seeds: torch.Tensor | None = None,
    max_pieces: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Play one game per seed; returns (lines [G], pieces [G], capped [G]).

    ``weights`` is [F] (one policy for all games) or [G, F] (one per game).
    """
    table = placement_table(rules.width)
    g = seeds.shape[0]
    nf = feature_size(feature_id, rules.width)
    check_weights(weights, nf, g)
    w = weights.detach().to(torch.float64).cpu()
    w = (w.expand(g, nf) if w.dim() == 1 else w).contiguous().numpy()
    ps = policy_seeds if policy_seeds is not None else seeds
    lines = np.zeros(g, np.int64)
    pieces = np.zeros(g, np.int64)
    capped = np.zeros(g, np.bool_)
    play_games(
        w,
        seeds.cpu().numpy().astype(np.int64),
        POLICY_RANDOM if random_policy else POLICY_LINEAR,
        ps.cpu().numpy().astype(np.int64),
        rules.width,
        rules.height,
        feature_id,
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
        lines,
        pieces,
        capped,
    )
    return torch.from_numpy(lines), torch.from_numpy(pieces), torch.from_numpy(capped)
