"""The seven tetrominoes, their distinct orientations and the placement table.

A placement is (orientation, column); placements are numbered orientation-major,
then column left to right, so that every engine enumerates them in the same order.
Cells are (row, col) with row 0 the piece's bottom row.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

PIECE_NAMES: tuple[str, ...] = ("I", "O", "T", "S", "Z", "L", "J")
NUM_PIECES = 7

# Spawn orientation of each piece, rows counted from the bottom of the piece.
_SPAWN: dict[str, tuple[tuple[int, int], ...]] = {
    "I": ((0, 0), (0, 1), (0, 2), (0, 3)),
    "O": ((0, 0), (0, 1), (1, 0), (1, 1)),
    "T": ((0, 0), (0, 1), (0, 2), (1, 1)),
    "S": ((0, 0), (0, 1), (1, 1), (1, 2)),
    "Z": ((0, 1), (0, 2), (1, 0), (1, 1)),
    "L": ((0, 0), (0, 1), (0, 2), (1, 2)),
    "J": ((0, 0), (0, 1), (0, 2), (1, 0)),
}


def _normalise(cells: list[tuple[int, int]]) -> tuple[tuple[int, int], ...]:
    r0 = min(r for r, _ in cells)
    c0 = min(c for _, c in cells)
    return tuple(sorted((r - r0, c - c0) for r, c in cells))


def _rotate_cw(cells: tuple[tuple[int, int], ...]) -> tuple[tuple[int, int], ...]:
    # (row up, col right) rotated clockwise: new_row = -col, new_col = row
    return _normalise([(-c, r) for r, c in cells])


def orientations(name: str) -> list[tuple[tuple[int, int], ...]]:
    """Distinct orientations of a piece, the spawn orientation first, then clockwise."""
    out: list[tuple[tuple[int, int], ...]] = []
    cur = _normalise(list(_SPAWN[name]))
    for _ in range(4):
        if cur not in out:
            out.append(cur)
        cur = _rotate_cw(cur)
    return out


def rotation_cycle(name: str) -> list[tuple[tuple[int, int], ...]]:
    """All four clockwise rotations (with repeats), as used by the primitive-move mode."""
    cur = _normalise(list(_SPAWN[name]))
    out = []
    for _ in range(4):
        out.append(cur)
        cur = _rotate_cw(cur)
    return out


@dataclass(frozen=True)
class PlacementTable:
    """Every placement of every piece on a board of a given width, as padded arrays.

    Shapes use A = the largest number of placements of any piece (34 on 10 wide).
    """

    width: int
    num_actions: np.ndarray  # [7] placements per piece
    max_actions: int
    column: np.ndarray  # [7, A] leftmost column of the placement
    orient: np.ndarray  # [7, A] orientation index
    row_masks: np.ndarray  # [7, A, 4] bitmask of the piece's cells per piece row, shifted to the column
    piece_height: np.ndarray  # [7, A]
    piece_width: np.ndarray  # [7, A]
    bottom: np.ndarray  # [7, A, 4] lowest filled piece row in each of the piece's columns (-1 = none)
    top: np.ndarray  # [7, A, 4] highest filled piece row + 1 in each of the piece's columns
    cells: np.ndarray  # [7, A, 4, 2] (row, col) of the four cells, col absolute


@functools.lru_cache(maxsize=64)
def placement_table(width: int) -> PlacementTable:
    """Build the placement table of all seven pieces for a board ``width`` columns wide."""
    per_piece: list[list[tuple[int, tuple[tuple[int, int], ...]]]] = []
    for name in PIECE_NAMES:
        acts = []
        for o, cells in enumerate(orientations(name)):
            w = max(c for _, c in cells) + 1
            for col in range(width - w + 1):
                acts.append((o, col, cells))
        per_piece.append(acts)
    a_max = max(len(a) for a in per_piece)
    num_actions = np.array([len(a) for a in per_piece], dtype=np.int64)
    column = np.zeros((7, a_max), np.int64)
    orient = np.zeros((7, a_max), np.int64)
    row_masks = np.zeros((7, a_max, 4), np.int64)
    piece_height = np.zeros((7, a_max), np.int64)
    piece_width = np.zeros((7, a_max), np.int64)
    bottom = np.full((7, a_max, 4), -1, np.int64)
    top = np.zeros((7, a_max, 4), np.int64)
    cells_arr = np.zeros((7, a_max, 4, 2), np.int64)
    for p, acts in enumerate(per_piece):
        for a, (o, col, cells) in enumerate(acts):
            column[p, a] = col
            orient[p, a] = o
            piece_height[p, a] = max(r for r, _ in cells) + 1
            piece_width[p, a] = max(c for _, c in cells) + 1
            for k, (r, c) in enumerate(cells):
                row_masks[p, a, r] |= 1 << (col + c)
                cells_arr[p, a, k] = (r, col + c)
                bottom[p, a, c] = r if bottom[p, a, c] < 0 else min(bottom[p, a, c], r)
                top[p, a, c] = max(top[p, a, c], r + 1)
    return PlacementTable(
        width=width,
        num_actions=num_actions,
        max_actions=a_max,
        column=column,
        orient=orient,
        row_masks=row_masks,
        piece_height=piece_height,
        piece_width=piece_width,
        bottom=bottom,
        top=top,
        cells=cells_arr,
    )
