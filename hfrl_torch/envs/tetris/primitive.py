"""Primitive-move Tetris (the thesis's TAMER description), batched in torch.

Actions: 0 move left, 1 move right, 2 rotate clockwise, 3 hard drop. After every action
other than a drop, gravity moves the falling piece down one row; a piece that cannot fall
locks. A move or rotation that would overlap the stack or leave the board is ignored
(no wall kicks). A rotation keeps the top-left corner of the piece's bounding box. Pieces
spawn in their spawn orientation at the top centre, where the placement engine's
spawn-zone check puts them; a piece that cannot spawn ends the game. Locking clears full
rows as the placement engine does (a locked piece never sticks out above the top, so the
game ends only at a spawn).
"""

from __future__ import annotations

import torch

from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, rotation_cycle
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.envs.tetris.sequence import game_key_t, piece_at_t

LEFT = 0
RIGHT = 1
ROTATE = 2
DROP = 3
NUM_ACTIONS = 4


def _shape_tables() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Local 4x4 cells [7, 4 rotations, 4 rows, 4 cols], heights, widths and column bottoms."""
    cells = torch.zeros(7, 4, 4, 4, dtype=torch.bool)
    bottom = torch.full((7, 4, 4), -1, dtype=torch.int64)
    for p, name in enumerate(PIECE_NAMES):
        for o, shape in enumerate(rotation_cycle(name)):
            for r, c in shape:
                cells[p, o, r, c] = True
                bottom[p, o, c] = r if bottom[p, o, c] < 0 else min(int(bottom[p, o, c]), r)
    height = cells.any(-1).sum(-1)
    width = cells.any(-2).sum(-1)
    return cells, height, width, bottom


class PrimitiveTetris:
    """A batch of ``batch`` boards played with primitive moves; state tensors live on ``device``.

    Public state: ``cells`` [B, H, W] bool (the locked stack), ``pieces``, ``keys``, ``index``
    [B] int64, ``alive`` [B] bool, and the falling piece's ``rot`` (index into
    ``pieces.rotation_cycle``), ``row`` (bottom row of its bounding box) and ``col`` (left column).
    """

    def __init__(self, rules: TetrisRules, batch: int, device: torch.device | str = "cpu") -> None:
        self.rules = rules
        self.batch = batch
        self.device = torch.device(device)
        dev = self.device
        shapes, ph, pw, bottom = _shape_tables()
        self._shapes, self._ph, self._pw, self._bottom = (
            shapes.to(dev),
            ph.to(dev),
            pw.to(dev),
            bottom.to(dev),
        )
        h, w = rules.height, rules.width
        self._r = torch.arange(h, device=dev)
        self._c = torch.arange(w, device=dev)
        self._k4 = torch.arange(4, device=dev)
        self._b = torch.arange(batch, device=dev)
        self.cells = torch.zeros(batch, h, w, dtype=torch.bool, device=dev)
        zeros = torch.zeros(batch, dtype=torch.int64, device=dev)
        self.pieces, self.keys, self.index = zeros.clone(), zeros.clone(), zeros.clone()
        self.rot, self.row, self.col = zeros.clone(), zeros.clone(), zeros.clone()
        self.alive = torch.zeros(batch, dtype=torch.bool, device=dev)

    def _mask(self, rot: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """Board cells [B, H, W] covered by the falling piece at (rot, row, col), clipped to the board."""
        lr = self._r.view(1, -1) - row.view(-1, 1)
        lc = self._c.view(1, -1) - col.view(-1, 1)
        inside = ((lr >= 0) & (lr < 4)).unsqueeze(-1) & ((lc >= 0) & (lc < 4)).unsqueeze(1)
        local = self._shapes[self.pieces, rot]
        b = self._b.view(-1, 1, 1)
        got = local[b, lr.clamp(0, 3).unsqueeze(-1), lc.clamp(0, 3).unsqueeze(1)]
        return got & inside

    def _fits(self, rot: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
        """True where the piece at (rot, row, col) lies inside the board and off the stack."""
        ph, pw = self._ph[self.pieces, rot], self._pw[self.pieces, rot]
        inside = (row >= 0) & (col >= 0) & (row + ph <= self.rules.height) & (col + pw <= self.rules.width)
        return inside & ~(self._mask(rot, row, col) & self.cells).flatten(1).any(-1)

    def _spawn(self, mask: torch.Tensor) -> None:
        """Put each masked board's current piece at the top centre; boards where it overlaps die."""
        zero = torch.zeros_like(self.rot)
        col = (self.rules.width - self._pw[self.pieces, 0]) // 2
        row = self.rules.height - self._ph[self.pieces, 0]
        self.rot = torch.where(mask, zero, self.rot)
        self.row = torch.where(mask, row, self.row)
        self.col = torch.where(mask, col, self.col)
        self.alive = self.alive & ~(mask & ~self._fits(self.rot, self.row, self.col))

    def reset(self, mask: torch.Tensor, seeds: torch.Tensor) -> None:
        """Start new games on the boards where ``mask`` is set, game b from ``seeds[b]``."""
        m = mask.to(self.device, torch.bool)
        s = seeds.to(self.device, torch.int64)
        self.cells = self.cells & ~m.view(-1, 1, 1)
        self.index = torch.where(m, 0, self.index)
        self.keys = torch.where(m, game_key_t(s), self.keys)
        self.pieces = torch.where(m, piece_at_t(self.keys, self.index, self.rules.bag), self.pieces)
        self.alive = self.alive | m
        self._spawn(m)

    def _drop_distance(self) -> torch.Tensor:
        """Rows the falling piece can fall straight down from where it is [B]."""
        n, h, w = self.cells.shape
        level = torch.arange(1, h + 1, device=self.device).view(1, h, 1)
        below = torch.cat(
            [
                torch.zeros(n, 1, w, dtype=torch.int64, device=self.device),
                (self.cells * level).cummax(1).values,
            ],
            dim=1,
        )
        bottom = self._bottom[self.pieces, self.rot]
        y0 = (self.row.unsqueeze(-1) + bottom).clamp(0, h)
        cols = (self.col.unsqueeze(-1) + self._k4).clamp(max=w - 1)
        hb = below[self._b.unsqueeze(-1), y0, cols]
        dist = torch.where(bottom >= 0, y0 - hb, h + 4)
        return dist.amin(-1)

    def step(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Apply one primitive action per live board; returns (lines cleared [B], piece locked [B])."""
        a = actions.to(self.device, torch.int64)
        live = self.alive
        rot1 = (self.rot + 1) % 4
        p = self.pieces
        row1 = self.row + self._ph[p, self.rot] - self._ph[p, rot1]
        rot = torch.where(a == ROTATE, rot1, self.rot)
        row = torch.where(a == ROTATE, row1, self.row)
        col = self.col + (a == RIGHT).to(torch.int64) - (a == LEFT).to(torch.int64)
        ok = live & (a != DROP) & self._fits(rot, row, col)
        self.rot = torch.where(ok, rot, self.rot)
        self.row = torch.where(ok, row, self.row)
        self.col = torch.where(ok, col, self.col)
        falls = self._fits(self.rot, self.row - 1, self.col)
        drop = self._drop_distance()
        self.row = torch.where(live & (a != DROP) & falls, self.row - 1, self.row)
        self.row = torch.where(live & (a == DROP), self.row - drop, self.row)
        locked = live & ((a == DROP) | ~falls)
        lines = self._lock(locked)
        return lines, locked

    def _lock(self, locked: torch.Tensor) -> torch.Tensor:
        """Merge the falling piece into the stack where ``locked``, clear full rows, spawn the next."""
        h = self.rules.height
        cells = self.cells | (self._mask(self.rot, self.row, self.col) & locked.view(-1, 1, 1))
        full = cells.all(-1)
        lines = full.sum(-1)
        order = torch.sort(full.to(torch.uint8), dim=1, stable=True).indices
        cells = cells.gather(1, order.unsqueeze(-1).expand_as(cells))
        self.cells = cells & (self._r.view(1, h) < (h - lines).view(-1, 1)).unsqueeze(-1)
        self.index = self.index + locked.to(torch.int64)
        self.pieces = torch.where(locked, piece_at_t(self.keys, self.index, self.rules.bag), self.pieces)
        self._spawn(locked)
        return lines

    def boards(self) -> torch.Tensor:
        """Locked cells [B, H, W] as bool, row 0 at the bottom (the falling piece not included)."""
        return self.cells.clone()

    def falling_cells(self) -> torch.Tensor:
        """Cells [B, H, W] of the falling piece (empty on finished boards)."""
        return self._mask(self.rot, self.row, self.col) & self.alive.view(-1, 1, 1)
