"""Batched pure-torch Tetris engine, the device-agnostic twin of :mod:`engine_numba`.

A board is ``H + 4`` rows of ``W`` bool cells (the 4 spare rows hold a piece that sticks
out above the top before its lines clear) plus the column heights. Every placement of
every board is evaluated at once: a placement only changes the 4 rows the piece lands
in (the "window"), so the landing row, full rows, lines and new column heights are
computed on ``[B, A, 4, W]`` tensors; the whole afterstate board ``[B, A, H+4, W]`` is
built only for the feature sets that look at every cell (Dellacherie, Dellacherie-Thiery).
Rules, features and piece sequences match :class:`engine_numba.NumbaEngine` exactly.
"""

from __future__ import annotations

import torch

from hfrl_torch.envs.tetris.engine_numba import SPARE_ROWS, check_weights, spawn_masks
from hfrl_torch.envs.tetris.features import BT, DELLACHERIE, DT, KNOX, feature_size
from hfrl_torch.envs.tetris.pieces import PlacementTable, placement_table
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.envs.tetris.sequence import game_key_t, piece_at_t, uniform_index_t

_BYTE_CELLS: dict[torch.device, torch.Tensor] = {}


def _bits_to_cells(masks: torch.Tensor, width: int) -> torch.Tensor:
    """Row bitmasks [...] int64 -> cells [..., W] bool, byte by byte through a lookup table."""
    lut = _BYTE_CELLS.get(masks.device)
    if lut is None:
        lut = (
            torch.arange(256, device=masks.device).unsqueeze(-1) >> torch.arange(8, device=masks.device)
        ) & 1
        lut = _BYTE_CELLS.setdefault(masks.device, lut.to(torch.bool))
    nbytes = (width + 7) // 8
    raw = masks.contiguous().unsqueeze(-1).view(torch.uint8)[..., :nbytes]
    return lut[raw.to(torch.int64)].flatten(-2)[..., :width]


def heights_below(cells: torch.Tensor) -> torch.Tensor:
    """[N, R+1, W]: entry r is the height of each column counting only rows below r."""
    n, nrows, width = cells.shape
    level = torch.arange(1, nrows + 1, device=cells.device).view(1, nrows, 1)
    top = (cells * level).cummax(dim=1).values
    return torch.cat([torch.zeros(n, 1, width, dtype=top.dtype, device=cells.device), top], dim=1)


def _popcount32(x: torch.Tensor) -> torch.Tensor:
    """Set bits of each int64 element below 2^32."""
    x = x - ((x >> 1) & 0x55555555)
    x = (x & 0x33333333) + ((x >> 2) & 0x33333333)
    x = (x + (x >> 4)) & 0x0F0F0F0F
    x = x + (x >> 8)
    return (x + (x >> 16)) & 0x3F


def _scan_or(rows: torch.Tensor, reverse: bool) -> torch.Tensor:
    """Inclusive OR-scan of [N, R] bitmasks along R (from the top if ``reverse``), by doubling."""
    n, nrows = rows.shape
    s = 1
    while s < nrows:
        pad = torch.zeros(n, s, dtype=rows.dtype, device=rows.device)
        if reverse:
            rows = rows | torch.cat([rows[:, s:], pad], dim=1)
        else:
            rows = rows | torch.cat([pad, rows[:, :-s]], dim=1)
        s *= 2
    return rows


def _last_filled(cells: torch.Tensor) -> torch.Tensor:
    """[N, R, W]: row of the highest filled cell at or below each cell (-1 if none), by doubling."""
    nrows = cells.shape[1]
    r = torch.arange(nrows, dtype=torch.int16, device=cells.device).view(1, nrows, 1)
    last = torch.where(cells, r, -1)
    s = 1
    while s < nrows:
        last[:, s:] = torch.maximum(last[:, s:], last[:, :-s])
        s *= 2
    return last


def board_features_t(
    fid: int,
    height: int,
    heights: torch.Tensor,
    filled: torch.Tensor,
    landing_height: torch.Tensor,
    eroded: torch.Tensor,
    rows: torch.Tensor | None,
    dtype: torch.dtype,
) -> torch.Tensor:
    """Feature set ``fid`` of N boards ([N, F] in ``dtype``), as ``engine_numba._features``.

    ``rows`` [N, H+4] (row bitmasks) is needed only by the Dellacherie sets. Squares of the
    Knox set are float32 squares then /100 in float64 when ``dtype`` is float32, as in numba.
    """
    n, width = heights.shape
    dev = heights.device
    if fid in (BT, KNOX):
        diffs = (heights[:, :-1] - heights[:, 1:]).abs()
        hmax = heights.amax(-1, keepdim=True)
        holes = (heights.sum(-1) - filled).unsqueeze(-1)
        base = torch.cat([heights, diffs, hmax, holes], dim=-1)
        if fid == BT:
            return base.to(dtype)
        wall = torch.full((n, 1), height, dtype=heights.dtype, device=dev)
        padded = torch.cat([wall, heights, wall], dim=-1)
        depth = (torch.minimum(padded[:, :-2], padded[:, 2:]) - heights).clamp(min=0)
        base = torch.cat([base, depth.amax(-1, keepdim=True), depth.sum(-1, keepdim=True)], dim=-1).to(dtype)
        if dtype == torch.float32:
            squares = ((base * base).to(torch.float64) / 100.0).to(torch.float32)
        else:
            squares = base * base / 100.0
        return torch.cat([base, squares], dim=-1)
    if fid not in (DELLACHERIE, DT) or rows is None:
        raise ValueError(f"feature id {fid} needs the board rows, or is unknown")
    full = (1 << width) - 1
    vis = rows[:, :height]
    x = (vis << 1) | (1 | (1 << (width + 1)))
    row_tr = _popcount32((x ^ (x >> 1)) & ((1 << (width + 1)) - 1)).sum(-1)
    prev = torch.cat([torch.full((n, 1), full, dtype=rows.dtype, device=dev), vis[:, :-1]], dim=1)
    col_tr = _popcount32(vis ^ prev).sum(-1)
    holes = heights.sum(-1) - filled
    well_bits = ~vis & full & ((vis << 1) | 1) & ((vis >> 1) | (1 << (width - 1)))
    cells = _bits_to_cells(vis, width)
    wells_at = _bits_to_cells(well_bits, width)
    r_vis = torch.arange(height, dtype=torch.int16, device=dev).view(1, height, 1)
    wells = ((r_vis - _last_filled(cells)) * wells_at).sum((1, 2))
    cols = [landing_height.to(dtype), eroded, row_tr, col_tr, holes, wells]
    if fid == DT:
        empty_below = _scan_or(~rows & full, reverse=False)
        empty_below = torch.cat([torch.zeros_like(empty_below[:, :1]), empty_below[:, :-1]], dim=1)
        hole_depth = _popcount32(rows & empty_below).sum(-1)
        filled_above = _scan_or(rows, reverse=True)
        filled_above = torch.cat([filled_above[:, 1:], torch.zeros_like(filled_above[:, :1])], dim=1)
        rows_with_holes = ((~rows & filled_above & full) != 0).sum(-1)
        d = heights[:, 1:] - heights[:, :-1]
        values = torch.arange(-2, 3, device=dev)
        diversity = (d.unsqueeze(-1) == values).any(1).sum(-1)
        cols += [hole_depth, rows_with_holes, diversity]
    return torch.stack([c.to(dtype) for c in cols], dim=-1)


class TorchEngine:
    """A batch of ``batch`` Tetris boards on ``device``, with the interface of ``NumbaEngine``.

    State: ``rows`` [B, H+4] int64 row bitmasks (bit c = column c, as in numba), ``heights``
    [B, W], ``pieces``, ``keys``, ``index`` [B] int64 and ``alive`` [B] bool, all on ``device``.
    """

    def __init__(
        self, rules: TetrisRules, batch: int, feature_id: int, device: torch.device | str = "cpu"
    ) -> None:
        self.rules = rules
        self.batch = batch
        self.fid = feature_id
        self.device = torch.device(device)
        self.table: PlacementTable = placement_table(rules.width)
        self.num_features = feature_size(feature_id, rules.width)
        dev = self.device
        t = self.table
        w = rules.width
        self.nrows = rules.height + SPARE_ROWS
        self._full = (1 << w) - 1
        self._num_actions = torch.as_tensor(t.num_actions, device=dev)
        self._valid = torch.arange(t.max_actions, device=dev) < self._num_actions.unsqueeze(-1)
        self._prow = torch.as_tensor(t.row_masks, device=dev)  # [7, A, 4]
        self._rowcount = _popcount32(self._prow)
        self._bottom = torch.as_tensor(t.bottom, device=dev)
        self._column = torch.as_tensor(t.column, device=dev)
        self._half_height = (torch.as_tensor(t.piece_height, device=dev) - 1) / 2.0
        self._spawn = torch.as_tensor(spawn_masks(t), device=dev)  # [7, 4]
        self._spawn_h = (self._spawn != 0).sum(-1)
        self._k4 = torch.arange(4, device=dev)
        self._colbit = torch.ones((), dtype=torch.int64, device=dev) << torch.arange(w, device=dev)
        self.rows = torch.zeros(batch, self.nrows, dtype=torch.int64, device=dev)
        self.heights = torch.zeros(batch, w, dtype=torch.int64, device=dev)
        self.pieces = torch.zeros(batch, dtype=torch.int64, device=dev)
        self.keys = torch.zeros(batch, dtype=torch.int64, device=dev)
        self.index = torch.zeros(batch, dtype=torch.int64, device=dev)
        self.alive = torch.zeros(batch, dtype=torch.bool, device=dev)

    def reset(self, mask: torch.Tensor, seeds: torch.Tensor) -> None:
        """Start new games on the boards where ``mask`` is set, game b from ``seeds[b]``."""
        m = mask.to(self.device, torch.bool)
        s = seeds.to(self.device, torch.int64)
        self.rows = torch.where(m.unsqueeze(-1), 0, self.rows)
        self.heights = torch.where(m.unsqueeze(-1), 0, self.heights)
        self.index = torch.where(m, 0, self.index)
        self.alive = self.alive | m
        self.keys = torch.where(m, game_key_t(s), self.keys)
        self.pieces = torch.where(
            m, piece_at_t(self.keys, torch.zeros_like(self.index), self.rules.bag), self.pieces
        )

    def _place(self, piece: torch.Tensor, action: torch.Tensor) -> dict[str, torch.Tensor]:
        """Drop placement ``action`` of ``piece`` ([B, K] each) onto every board, window-wise.

        A placement only touches the 4 rows from its landing row up: returns land, those rows
        after placing [B,K,4], which are full, lines, piece cells removed, new heights [B,K,W]
        and game over, without building the whole afterstate board.
        """
        b, k = action.shape
        w = self.rules.width
        nrows = self.nrows
        k4 = self._k4
        bottom = self._bottom[piece, action]
        col = self._column[piece, action]
        cidx = (col.unsqueeze(-1) + k4).clamp(max=w - 1)
        h = self.heights.gather(1, cidx.view(b, k * 4)).view(b, k, 4)
        land = torch.where(bottom >= 0, h - bottom, 0).amax(-1).clamp(0, nrows - SPARE_ROWS)
        win_rows = land.unsqueeze(-1) + k4
        win = self.rows.gather(1, win_rows.view(b, k * 4)).view(b, k, 4) | self._prow[piece, action]
        full = win == self._full
        lines = full.sum(-1)
        removed = (self._rowcount[piece, action] * full).sum(-1)
        top = win_rows - (full.cumsum(-1) - full.to(torch.int64)) + 1
        kept = torch.where(full, 0, win)
        cand = torch.zeros(b, k, w, dtype=torch.int64, device=self.device)
        for i in range(4):
            occupied = (kept[..., i : i + 1] & self._colbit) != 0
            cand = torch.where(occupied, top[..., i : i + 1], cand)
        hb_id = (torch.arange(b, device=self.device).view(b, 1) * (nrows + 1) + land).view(-1)
        below = self._hbelow.view(b * (nrows + 1), w).index_select(0, hb_id).view(b, k, w)
        old = self.heights.unsqueeze(1)
        new_h = torch.where(
            old > (land + 4).unsqueeze(-1), old - lines.unsqueeze(-1), torch.maximum(cand, below)
        )
        over = (new_h > self.rules.height).any(-1)
        return {
            "land": land,
            "win": win,
            "full": full,
            "lines": lines,
            "removed": removed,
            "heights": new_h,
            "over": over,
        }

    def _materialize(self, res: dict[str, torch.Tensor]) -> torch.Tensor:
        """Whole afterstate boards as row bitmasks [B, K, H+4] from the result of :meth:`_place`."""
        land, win, full, lines = res["land"], res["win"], res["full"], res["lines"]
        b, k = land.shape
        nrows = self.nrows
        d = torch.arange(nrows, device=self.device)
        j = d - land.unsqueeze(-1)
        in_win = (j >= 0) & (j < (4 - lines).unsqueeze(-1))
        src = torch.where(j < 0, d, d + lines.unsqueeze(-1))
        keep_old = (src < nrows) & ~in_win
        old = self.rows.gather(1, src.clamp(max=nrows - 1).view(b, k * nrows)).view(b, k, nrows)
        kept_index = ((~full).cumsum(-1).unsqueeze(-2) <= self._k4.view(4, 1)).sum(-1).clamp(max=3)
        new = win.gather(-1, kept_index.gather(-1, j.clamp(0, 3)))
        return torch.where(keep_old, old, 0) | torch.where(in_win, new, 0)

    def _cells(self) -> torch.Tensor:
        return _bits_to_cells(self.rows, self.rules.width)

    def _afterstates(
        self, dtype: torch.dtype
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        b = self.batch
        a = self.table.max_actions
        w = self.rules.width
        self._hbelow = heights_below(self._cells())
        piece = self.pieces.unsqueeze(-1).expand(b, a)
        action = torch.arange(a, device=self.device).expand(b, a)
        res = self._place(piece, action)
        lines = res["lines"]
        filled = _popcount32(self.rows).sum(-1, keepdim=True) + 4 - lines * w
        lh = res["land"] + 1 + self._half_height[piece, action]
        rows = self._materialize(res).view(b * a, self.nrows) if self.fid in (DELLACHERIE, DT) else None
        feats = board_features_t(
            self.fid,
            self.rules.height,
            res["heights"].view(b * a, w),
            filled.view(-1),
            lh.view(-1),
            (lines * res["removed"]).view(-1),
            rows,
            dtype,
        ).view(b, a, -1)
        mask = self._valid[self.pieces] & self.alive.unsqueeze(-1)
        feats = torch.where(mask.unsqueeze(-1), feats, 0)
        return feats, mask, res["over"] & mask, torch.where(mask, lines, 0)

    def afterstates(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(features [B,A,F] float32, valid mask [B,A], game-ending [B,A], lines cleared [B,A])."""
        return self._afterstates(torch.float32)

    def board_features(self) -> torch.Tensor:
        """Features [B, F] of the current boards (landing height and eroded cells are 0)."""
        zeros = torch.zeros(self.batch, dtype=torch.int64, device=self.device)
        return board_features_t(
            self.fid,
            self.rules.height,
            self.heights,
            _popcount32(self.rows).sum(-1),
            zeros.to(torch.float64),
            zeros,
            self.rows,
            torch.float32,
        )

    def _spawn_blocked(self, rows: torch.Tensor, pieces: torch.Tensor) -> torch.Tensor:
        """True where ``pieces`` in spawn orientation at the top centre overlaps ``rows`` [B, R]."""
        at = (self.rules.height - self._spawn_h[pieces]).unsqueeze(-1) + self._k4
        return ((rows.gather(1, at) & self._spawn[pieces]) != 0).any(-1)

    def step(self, actions: torch.Tensor) -> torch.Tensor:
        """Place the current piece of every live board; returns lines cleared [B]."""
        a = actions.to(self.device, torch.int64).clamp(0, self.table.max_actions - 1)
        self._hbelow = heights_below(self._cells())
        res = self._place(self.pieces.unsqueeze(-1), a.unsqueeze(-1))
        after = self._materialize(res)[:, 0]
        live = self.alive
        self.rows = torch.where(live.unsqueeze(-1), after, self.rows)
        self.heights = torch.where(live.unsqueeze(-1), res["heights"][:, 0], self.heights)
        lines = torch.where(live, res["lines"][:, 0], 0)
        self.index = self.index + live.to(torch.int64)
        self.pieces = torch.where(live, piece_at_t(self.keys, self.index, self.rules.bag), self.pieces)
        over = res["over"][:, 0]
        if self.rules.spawn_topout:
            over = over | self._spawn_blocked(after, self.pieces)
        self.alive = live & ~over
        return lines

    def boards(self) -> torch.Tensor:
        """Cells [B, H, W] as bool, row 0 at the bottom."""
        return _bits_to_cells(self.rows[:, : self.rules.height], self.rules.width)

    def next_pieces(self) -> torch.Tensor:
        """The piece after the current one [B] (for the preview option)."""
        return piece_at_t(self.keys, self.index + 1, self.rules.bag)

    def state_tensors(self) -> dict[str, torch.Tensor]:
        """The whole engine state as tensors, in the layout of ``NumbaEngine.state_tensors``."""
        names = ("rows", "heights", "pieces", "keys", "index", "alive")
        return {name: getattr(self, name).clone() for name in names}

    def _take(self, idx: torch.Tensor) -> None:
        """Keep only the boards ``idx`` (used by :func:`play` to drop finished games)."""
        for name in ("rows", "heights", "pieces", "keys", "index", "alive"):
            setattr(self, name, getattr(self, name)[idx])
        self.batch = int(idx.shape[0])


def _linear_values(
    feats: torch.Tensor, mask: torch.Tensor, terminal: torch.Tensor, w: torch.Tensor
) -> torch.Tensor:
    """w . f summed feature by feature in float64 (the numba order); invalid and avoidable game-ending
    placements get -inf."""
    v = torch.zeros(feats.shape[:2], dtype=torch.float64, device=feats.device)
    for k in range(feats.shape[-1]):
        v = v + w[:, k : k + 1] * feats[..., k]
    return _exclude(v, mask, terminal)


def _exclude(v: torch.Tensor, mask: torch.Tensor, terminal: torch.Tensor) -> torch.Tensor:
    safe = mask & ~terminal
    keep = torch.where(safe.any(-1, keepdim=True), safe, mask)
    return torch.where(keep, v, -torch.inf)


def play(
    rules: TetrisRules,
    feature_id: int,
    weights: torch.Tensor,
    seeds: torch.Tensor,
    *,
    random_policy: bool = False,
    policy_seeds: torch.Tensor | None = None,
    max_pieces: int = 0,
    device: torch.device | str = "cpu",
    chunk: int = 4096,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Play one game per seed; returns (lines [G], pieces [G], capped [G]) on the CPU.

    Same contract as ``engine_numba.play``: ``weights`` is [F] or [G, F]; the linear policy
    takes the first placement of highest ``w . f`` and a game-ending one only when all are;
    ``max_pieces`` > 0 caps games. Games run ``chunk`` at a time; finished games are dropped
    from the batch as they end so that the long games' late steps stay cheap.
    """
    dev = torch.device(device)
    g = seeds.shape[0]
    nf = feature_size(feature_id, rules.width)
    check_weights(weights, nf, g)
    w_all = weights.detach().to(dev, torch.float64)
    w_all = w_all.expand(g, nf) if w_all.dim() == 1 else w_all
    ps_all = (policy_seeds if policy_seeds is not None else seeds).to(dev, torch.int64)
    out_lines = torch.zeros(g, dtype=torch.int64, device=dev)
    out_pieces = torch.zeros(g, dtype=torch.int64, device=dev)
    out_capped = torch.zeros(g, dtype=torch.bool, device=dev)
    for start in range(0, g, chunk):
        gid = torch.arange(start, min(start + chunk, g), device=dev)
        n = gid.shape[0]
        eng = TorchEngine(rules, n, feature_id, dev)
        eng.reset(torch.ones(n, dtype=torch.bool, device=dev), seeds.to(dev, torch.int64)[gid])
        w = w_all[gid]
        pkey = game_key_t(ps_all[gid])
        lines = torch.zeros(n, dtype=torch.int64, device=dev)
        t = 0
        while True:
            if max_pieces > 0 and t >= max_pieces:
                out_capped[gid] = eng.alive
                break
            feats, mask, term, _ = eng._afterstates(torch.float64)
            if random_policy:
                act = uniform_index_t(pkey, eng.index, eng._num_actions[eng.pieces])
            else:
                act = _linear_values(feats, mask, term, w).argmax(-1)
            lines = lines + eng.step(act)
            t += 1
            if t % 8 == 0:
                alive = eng.alive.nonzero().squeeze(-1)
                if alive.shape[0] == 0:
                    break
                if 2 * alive.shape[0] <= eng.batch:
                    out_lines[gid] = lines
                    out_pieces[gid] = eng.index
                    eng._take(alive)
                    gid, w, pkey, lines = gid[alive], w[alive], pkey[alive], lines[alive]
        out_lines[gid] = lines
        out_pieces[gid] = eng.index
    return out_lines.cpu(), out_pieces.cpu(), out_capped.cpu()
