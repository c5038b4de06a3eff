"""Feature sets of the numba Tetris engine (BT 21, Knox 46, Dellacherie 6, Dellacherie-Thiery 9).

Expected values are worked out by hand in the comments, on small boards written as
pictures (top row first, ``X`` = filled, the last line is row 0). Boards are loaded by
setting ``NumbaEngine.rows`` (bit c = column c) and ``heights`` directly.
Reference: /work/shared/specs/tetris.md, "Features".
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hfrl_torch.envs.tetris.engine_numba import NumbaEngine, play
from hfrl_torch.envs.tetris.features import (
    BT,
    DELLACHERIE,
    DELLACHERIE_WEIGHTS,
    DT,
    KNOX,
    feature_names,
    feature_size,
)
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, orientations, placement_table
from hfrl_torch.envs.tetris.rules import TetrisRules

# ---------------------------------------------------------------- helpers


def parse_board(picture: list[str], width: int) -> tuple[list[int], list[int]]:
    """(row bitmasks with row 0 first, column heights) of a picture given top row first."""
    assert all(len(line) == width for line in picture), picture
    rows = [sum(1 << c for c, ch in enumerate(line) if ch == "X") for line in reversed(picture)]
    heights = [max((r + 1 for r, row in enumerate(rows) if row >> c & 1), default=0) for c in range(width)]
    return rows, heights


def make_engine(
    width: int, height: int, fid: int, pictures: list[list[str]], piece: str = "I"
) -> NumbaEngine:
    eng = NumbaEngine(TetrisRules(width=width, height=height), len(pictures), fid)
    eng.reset(torch.ones(len(pictures), dtype=torch.bool), torch.arange(len(pictures), dtype=torch.int64))
    for b, picture in enumerate(pictures):
        rows, heights = parse_board(picture, width)
        eng.rows[b] = 0
        eng.rows[b, : len(rows)] = rows
        eng.heights[b] = heights
        eng.pieces[b] = PIECE_NAMES.index(piece)
    return eng


def action(width: int, piece: str, shape: str, col: int) -> int:
    """Placement index of ``piece`` in orientation ``shape`` (e.g. ``"X./XX/.X"``) at column ``col``."""
    lines = shape.split("/")
    cells = tuple(
        sorted(
            (len(lines) - 1 - i, c) for i, line in enumerate(lines) for c, ch in enumerate(line) if ch == "X"
        )
    )
    table = placement_table(width)
    p = PIECE_NAMES.index(piece)
    o = orientations(piece).index(cells)
    for a in range(int(table.num_actions[p])):
        if table.orient[p, a] == o and table.column[p, a] == col:
            return a
    raise AssertionError(f"no placement {piece} {shape} at column {col}")


def board_feats(width: int, height: int, fid: int, pictures: list[list[str]]) -> list[list[float]]:
    return make_engine(width, height, fid, pictures).board_features().tolist()


def after_feats(width: int, height: int, fid: int, picture: list[str], piece: str, shape: str, col: int):
    """(features, lines, terminal) of one placement's afterstate."""
    eng = make_engine(width, height, fid, [picture], piece)
    feats, mask, terminal, lines = eng.afterstates()
    a = action(width, piece, shape, col)
    assert mask[0, a]
    return feats[0, a].tolist(), int(lines[0, a]), bool(terminal[0, a])


def squares(values: list[float]) -> list[float]:
    return [v * v / 100.0 for v in values]


# Board B1, 6 wide x 6 high. Columns: 0 rows 0-2 (height 3); 1 rows 0,2,3,4 (height 5, hole at row 1);
# 2 empty; 3 rows 0-2 (3); 4 rows 0-3 (4); 5 rows 0-1 (2). 16 filled cells, heights sum 17: 1 hole.
B1 = [
    "......",  # row 5
    ".X....",  # row 4
    ".X..X.",  # row 3
    "XX.XX.",  # row 2
    "X..XXX",  # row 1
    "XX.XXX",  # row 0
]
# Board B2, 6 x 6. Column 0: rows 1,3,4 (height 5, holes at rows 0 and 2); 1: rows 0-2 (3); 2: row 0 (1);
# 3: rows 0,1,3 (height 4, hole at row 2); 4: rows 0-1 (2); 5 empty. 12 cells, heights sum 15: 3 holes.
B2 = [
    "......",  # row 5
    "X.....",  # row 4
    "X..X..",  # row 3
    ".X....",  # row 2
    "XX.XX.",  # row 1
    ".XXXX.",  # row 0
]


# ---------------------------------------------------------------- sizes


def test_feature_sizes_and_names():
    assert [feature_size(f, 10) for f in (BT, KNOX, DELLACHERIE, DT)] == [21, 46, 6, 9]
    assert [feature_size(f, 6) for f in (BT, KNOX, DELLACHERIE, DT)] == [13, 30, 6, 9]
    for f in (BT, KNOX, DELLACHERIE, DT):
        names = feature_names(f, 10)
        assert len(names) == feature_size(f, 10) and len(set(names)) == len(names)


# ---------------------------------------------------------------- BT and Knox


def test_bt_features_hand_boards():
    # B1: heights 3 5 0 3 4 2; |diffs| |3-5|=2 |5-0|=5 |0-3|=3 |3-4|=1 |4-2|=2; max 5; holes 1
    # B2: heights 5 3 1 4 2 0; |diffs| 2 2 3 2 2; max 5; holes 3
    got = board_feats(6, 6, BT, [B1, B2])
    assert got[0] == [3, 5, 0, 3, 4, 2, 2, 5, 3, 1, 2, 5, 1]
    assert got[1] == [5, 3, 1, 4, 2, 0, 2, 2, 3, 2, 2, 5, 3]


def test_bt_features_ten_wide():
    # heights 3 1 0 2 1 0 2 1 1 2 (column 6 has a hole at row 0); 12 cells, sum 13 -> 1 hole
    board = [
        "X.........",
        "X..X..X..X",
        "XX.XX..XXX",
    ]
    diffs = [2, 1, 2, 1, 1, 2, 1, 0, 1]
    (got,) = board_feats(10, 10, BT, [board])
    assert got == [3, 1, 0, 2, 1, 0, 2, 1, 1, 2, *diffs, 3, 1]
    # Knox wells (walls = 10): column 2: min(1, 2) - 0 = 1; column 5: min(1, 2) - 0 = 1; columns 7, 8:
    # min(2,1)-1 = 0, min(1,2)-1 = 0; edges: min(10, 1) - 3 < 0, min(1, 10) - 2 < 0. Max 1, sum 2.
    (knox,) = board_feats(10, 10, KNOX, [board])
    base = [*got, 1, 2]
    assert knox == pytest.approx(base + squares(base), rel=1e-6)


def test_knox_features_hand_board():
    # B1 wells with the walls as high as the board (6): column 0: min(6, 5) - 3 = 2; column 2:
    # min(5, 3) - 0 = 3; column 5: min(4, 6) - 2 = 2; columns 1, 3, 4 are above a neighbour. Max 3, sum 7.
    (got,) = board_feats(6, 6, KNOX, [B1])
    base = [3, 5, 0, 3, 4, 2, 2, 5, 3, 1, 2, 5, 1, 3, 7]
    assert len(got) == 30
    assert got == pytest.approx(base + squares(base), rel=1e-6)
    assert got[15 + 1] == pytest.approx(0.25)  # height 5 squared / 100


def test_knox_wall_wells():
    # 4 x 5, heights 0 3 3 1: edge column 0 is a well of depth min(wall 5, 3) - 0 = 3, edge column 3 of
    # depth min(3, wall 5) - 1 = 2 (a wall counting as height 0 would give no edge wells at all).
    board = [
        ".XX.",
        ".XX.",
        ".XXX",
    ]
    (got,) = board_feats(4, 5, KNOX, [board])
    base = [0, 3, 3, 1, 3, 0, 2, 3, 0, 3, 5]
    assert got == pytest.approx(base + squares(base), rel=1e-6)


def test_empty_board():
    # 10 x 20 empty: BT all 0; Knox all 0 (edge columns: min(20, 0) - 0 = 0); Dellacherie: each of the
    # 20 empty rows has 2 transitions (wall|empty, empty|wall) = 40; each column 1 (floor|empty) = 10.
    assert board_feats(10, 20, BT, [[]])[0] == [0] * 21
    assert board_feats(10, 20, KNOX, [[]])[0] == [0] * 46
    assert board_feats(10, 20, DELLACHERIE, [[]])[0] == [0, 0, 40, 10, 0, 0]
    assert board_feats(10, 20, DT, [[]])[0] == [0, 0, 40, 10, 0, 0, 0, 0, 1]  # all diffs 0: 1 pattern


# ---------------------------------------------------------------- Dellacherie and Dellacherie-Thiery


def test_dellacherie_features_hand_boards():
    # B1 row transitions (walls filled; W = wall):
    #   row 0 W XX.XXX W: 2 | row 1 W X..XXX W: 2 | row 2 W XX.XX. W: 4 | row 3 W .X..X. W: 6
    #   row 4 W .X.... W: 4 | row 5 empty: 2                                    -> 20
    # column transitions (floor filled, bottom to top): col 0 111000: 1; col 1 101110: 3; col 2: 1;
    #   col 3 111000: 1; col 4 111100: 1; col 5 110000: 1                          -> 8
    # holes: 1 (column 1, row 1)
    # cumulative wells (cell empty, both neighbours filled or wall; counts 1 + empty cells below it):
    #   col 0 (wall | col 1): rows 3 (1, row 2 below is full) and 4 (2)      = 3
    #   col 2 (col 1 | col 3): row 2 (1 + rows 1, 0 empty = 3) and row 0 (1); row 1 is not a well
    #         cell (column 1 is empty there)                                 = 4
    #   col 5 (col 4 | wall): rows 2 (1) and 3 (2)                           = 3   -> 10
    # B2 row transitions: .XXXX. 4 | XX.XX. 4 | .X.... 4 | X..X.. 4 | X..... 2 | empty 2 -> 20
    #   column transitions: col 0 (floor) 0 1 0 1 1 0: 5; col 1: 1; col 2: 1; col 3 1 1 0 1 0 0: 3;
    #   col 4: 1; col 5: 1                                                               -> 12
    #   holes 3; wells: col 0 rows 0 (1) and 2 (1); col 2 row 1 (1); col 5 rows 0 (1) and 1 (2)  -> 6
    got = board_feats(6, 6, DELLACHERIE, [B1, B2])
    # board features have no placement: landing height and eroded cells are 0
    assert got[0] == [0, 0, 20, 8, 1, 10]
    assert got[1] == [0, 0, 20, 12, 3, 6]


def test_dellacherie_thiery_extras():
    # B1: hole depth = full cells directly above the hole at column 1 row 1: rows 2, 3, 4 -> 3;
    #     rows with holes: row 1 -> 1; height differences h[c+1]-h[c]: 2 -5 3 1 -2 -> {2, 1, -2}: 3 patterns
    # B2: column 0 holes at rows 2 (full run above: rows 3, 4 -> 2) and 0 (run above: row 1 -> 1), column 3
    #     hole at row 2 (row 3 -> 1): hole depth 4; rows with holes: rows 0 and 2 -> 2;
    #     differences -2 -2 3 -2 -2 -> {-2}: 1 pattern
    got = board_feats(6, 6, DT, [B1, B2])
    assert got[0] == [0, 0, 20, 8, 1, 10, 3, 1, 3]
    assert got[1] == [0, 0, 20, 12, 3, 6, 4, 2, 1]


def test_pattern_diversity():
    # heights 0 2 3 3 2 0 0 5 0 0: differences 2 1 0 -1 -2 0 5 -5 0 -> all five of -2..2
    stairs = [
        "".join("X" if h > r else "." for h in (0, 2, 3, 3, 2, 0, 0, 5, 0, 0)) for r in reversed(range(5))
    ]
    # heights 0 3 6 9: differences of 3 only -> none counts
    steep = ["".join("X" if h > r else "." for h in (0, 3, 6, 9)) for r in reversed(range(9))]
    assert board_feats(10, 10, DT, [stairs])[0][8] == 5
    assert board_feats(4, 10, DT, [steep])[0][8] == 0


@pytest.mark.parametrize("depth", [1, 2, 3, 4])
def test_clean_well_scores_triangular_number(depth):
    # 4 x 6: columns 0-2 full to `depth`, column 3 empty: a well against the right wall of depth d.
    # Its cells, from the top, count d, d-1, ..., 1: d (d + 1) / 2. Row transitions: 2 per row (XXX. or
    # empty) = 12; column transitions: 1 per column = 4; no holes.
    edge = ["XXX."] * depth
    # the same well in the middle of a 5-wide board
    middle = ["XX.XX"] * depth
    tri = depth * (depth + 1) // 2
    assert board_feats(4, 6, DELLACHERIE, [edge])[0] == [0, 0, 12, 4, 0, tri]
    assert board_feats(5, 6, DELLACHERIE, [middle])[0][5] == tri


def test_afterstate_features_with_a_line_clear():
    # B1 + upright I in column 2 (height 0): it lands on row 0 and fills rows 0-3 of column 2. Row 0 becomes
    # full and clears (1 line, 1 of the piece's cells: eroded 1 x 1 = 1). Landing height, 1-based bottom row
    # + (4 - 1) / 2 = 1 + 1.5 = 2.5. The afterstate:
    #   row 3 .X....
    #   row 2 .XX.X.
    #   row 1 XXXXX.
    #   row 0 X.XXXX      heights 2 4 3 2 3 1, 14 cells, 1 hole (column 1 row 0)
    # row transitions: row 0: 2, row 1: 2, row 2: 6, row 3: 4, rows 4-5: 2 + 2 -> 18
    # column transitions: 1 + 3 (col 1: 0 1 1 1 0 over the floor) + 1 + 1 + 1 + 1 -> 8
    # wells: col 0 rows 2 (1) and 3 (2); col 1 row 0 (1, between columns 0 and 2); col 3 row 2 (1);
    #   col 5 rows 1 (1) and 2 (2) -> 8
    # DT: hole depth 3 (column 1 rows 1-3 over the hole), rows with holes 1, differences 2 -1 -1 1 -2 -> 4
    feats, lines, terminal = after_feats(6, 6, DT, B1, "I", "X/X/X/X", 2)
    assert (lines, terminal) == (1, False)
    assert feats == [2.5, 1, 18, 8, 1, 8, 3, 1, 4]
    bt, _, _ = after_feats(6, 6, BT, B1, "I", "X/X/X/X", 2)
    assert bt == [2, 4, 3, 2, 3, 1, 2, 1, 1, 1, 2, 4, 1]


def test_landing_height_convention():
    # landing height = 1-based row of the piece's bottom + (piece height - 1) / 2
    empty: list[str] = []
    cases = [
        ("I", "XXXX", 0, empty, 1.0),  # bottom row 1, height 1
        ("I", "X/X/X/X", 0, empty, 2.5),  # 1 + 3/2
        ("O", "XX/XX", 4, empty, 1.5),
        ("T", ".X./XXX", 0, empty, 1.5),
        ("L", "X./X./XX", 3, empty, 2.0),  # 1 + 2/2
    ]
    stepped = [
        "X.........",
        "XX........",
        "XXX....X..",
        "XXXX..XX..",
    ]
    cases += [
        ("T", "XXX/.X.", 2, stepped, 2.5),  # lands on row 1 (0-based): 2 + 1/2
        ("O", "XX/XX", 0, stepped, 5.5),  # lands on row 4: 5 + 1/2
        ("Z", "XX./.XX", 5, stepped, 3.5),  # lands on row 2: 3 + 1/2
    ]
    for piece, shape, col, board, want in cases:
        feats, lines, _ = after_feats(10, 20, DELLACHERIE, board, piece, shape, col)
        assert feats[0] == want, (piece, shape, col)
        assert feats[1] == 0 and lines == 0


def test_eroded_piece_cells():
    cases = [
        # board, piece, shape, column, lines, eroded = lines x piece cells removed
        (["XXXXXXX..."], "L", "..X/XXX", 7, 1, 1 * 3),
        (["XXXXXXXXX."], "S", "X./XX/.X", 8, 1, 1 * 1),  # only the S's lowest cell is in row 0
        (["XXXXXXXX.."] * 2, "O", "XX/XX", 8, 2, 2 * 4),
        (["XXXXXXXXX."] * 2, "I", "X/X/X/X", 9, 2, 2 * 2),
        (["XXXXXXXXX."] * 3, "I", "X/X/X/X", 9, 3, 3 * 3),
        (["XXXXXXXXX."] * 4, "I", "X/X/X/X", 9, 4, 4 * 4),
    ]
    for board, piece, shape, col, n_lines, eroded in cases:
        feats, lines, terminal = after_feats(10, 20, DELLACHERIE, board, piece, shape, col)
        assert (lines, terminal) == (n_lines, False)
        assert feats[1] == eroded, (piece, shape)
    # the L case in full: the L's top cell drops to row 0, column 9. Landing height 1 + 1/2; row 0
    # ".........X" has 2 row transitions plus 2 x 19 empty rows = 40; 10 column transitions; no holes, wells.
    feats, _, _ = after_feats(10, 20, DELLACHERIE, ["XXXXXXX..."], "L", "..X/XXX", 7)
    assert feats == [1.5, 3, 40, 10, 0, 0]


# ---------------------------------------------------------------- against a plain reference


def reference_features(cells: np.ndarray) -> dict[str, object]:
    """Straight-from-the-spec features of a board given as cells[row, col] (row 0 at the bottom)."""
    h_rows, w = cells.shape
    heights = [max((r + 1 for r in range(h_rows) if cells[r, c]), default=0) for c in range(w)]
    holes = sum(1 for c in range(w) for r in range(heights[c]) if not cells[r, c])
    padded = np.ones((h_rows, w + 2), bool)
    padded[:, 1:-1] = cells
    row_tr = int(sum((padded[r, 1:] != padded[r, :-1]).sum() for r in range(h_rows)))
    floor = np.vstack([np.ones((1, w), bool), cells])
    col_tr = int((floor[1:] != floor[:-1]).sum())
    wells = 0
    for c in range(w):
        for r in range(h_rows):
            if not cells[r, c] and padded[r, c] and padded[r, c + 2]:
                k = r
                while k >= 0 and not cells[k, c]:
                    wells += 1
                    k -= 1
    depth = 0
    for c in range(w):
        for r in range(heights[c]):
            if not cells[r, c]:
                k = r + 1
                while k < h_rows and cells[k, c]:
                    depth += 1
                    k += 1
    rows_with_holes = sum(
        1 for r in range(h_rows) if any(not cells[r, c] and r < heights[c] for c in range(w))
    )
    diffs = {heights[c + 1] - heights[c] for c in range(w - 1)} & {-2, -1, 0, 1, 2}
    walls = [h_rows, *heights, h_rows]
    knox_wells = [max(min(walls[c], walls[c + 2]) - heights[c], 0) for c in range(w)]
    bt = heights + [abs(heights[c] - heights[c + 1]) for c in range(w - 1)] + [max(heights), holes]
    return {
        "bt": bt,
        "knox": [*bt, max(knox_wells), sum(knox_wells)],
        "dt": [0, 0, row_tr, col_tr, holes, wells, depth, rows_with_holes, len(diffs)],
    }


def test_board_features_match_a_plain_reference_on_played_boards():
    # boards met while playing 8 games of random placements on 10 x 12 (deterministic): every live board
    # after every placement, many with holes, wells and overhangs
    n, w, h = 8, 10, 12
    rng = np.random.default_rng(0)
    eng = NumbaEngine(TetrisRules(width=w, height=h), n, BT)
    eng.reset(torch.ones(n, dtype=torch.bool), torch.arange(n, dtype=torch.int64))
    rows, heights = [], []
    while eng.alive.any():
        acts = [
            int(rng.integers(eng.table.num_actions[p])) if a else 0
            for p, a in zip(eng.pieces, eng.alive, strict=True)
        ]
        eng.step(torch.tensor(acts, dtype=torch.int64))
        rows += list(eng.rows[eng.alive])
        heights += list(eng.heights[eng.alive])
    assert len(rows) >= 40
    feats = {}
    for fid in (BT, KNOX, DT):
        other = NumbaEngine(TetrisRules(width=w, height=h), len(rows), fid)
        other.rows[:] = np.stack(rows)
        other.heights[:] = np.stack(heights)
        feats[fid] = other.board_features().numpy()
    cells = other.boards().numpy()
    with_holes = 0
    for b in range(len(rows)):
        ref = reference_features(cells[b])
        assert feats[BT][b].tolist() == ref["bt"]
        assert feats[KNOX][b, :23].tolist() == ref["knox"]
        np.testing.assert_allclose(feats[KNOX][b, 23:], np.square(ref["knox"]) / 100.0, rtol=1e-6)
        assert feats[DT][b].tolist() == ref["dt"]
        with_holes += ref["bt"][-1] > 0
    assert with_holes >= 10  # the comparison covered boards with holes


# ---------------------------------------------------------------- policies


def test_dellacherie_weights_clear_many_lines():
    # Measured on 10 x 10 with seeds 0..19: mean 1838 lines (per game 116 .. 6344), about 0.5 s.
    # Lines per game are about exponential, so a 20-game mean has a standard deviation of about
    # 1838 / sqrt(20) = 411: the threshold 500 is more than 3 s.d. below the measured mean, yet a broken
    # feature (sign, off-by-one in wells or transitions) costs factors of 10 and more. For scale: the spec's
    # "millions on 10 x 20" and "about 4x per 2 extra rows" give 1e6 / 4**5 ~ 1000 on 10 x 10.
    rules = TetrisRules(width=10, height=10)
    w = torch.tensor(DELLACHERIE_WEIGHTS)
    seeds = torch.arange(20)
    lines, pieces, capped = play(rules, DELLACHERIE, w, seeds)
    assert not capped.any()
    assert lines.float().mean() > 500
    assert (lines > 0).all()
    # deterministic: the same seeds play the same games
    lines2, pieces2, _ = play(rules, DELLACHERIE, w, seeds)
    assert torch.equal(lines, lines2) and torch.equal(pieces, pieces2)
    # every piece brings 4 cells and every line removes 10; an ended game holds at most 10 x (10 + 4) cells
    left = 4 * pieces - 10 * lines
    assert (left >= 0).all() and (left <= 140).all()


def test_random_policy_clears_almost_nothing():
    # measured: 0 lines in 100 games on 10 x 10, 9.7 pieces per game on average
    rules = TetrisRules(width=10, height=10)
    lines, pieces, capped = play(
        rules,
        DELLACHERIE,
        torch.tensor(DELLACHERIE_WEIGHTS),
        torch.arange(100),
        random_policy=True,
        max_pieces=1000,
    )
    assert not capped.any()
    assert lines.float().mean() < 0.5
    assert pieces.float().mean() < 20


def test_max_pieces_cap():
    # the Dellacherie player survives 100 pieces on 10 x 10 for these seeds; the cap stops every game at 100
    # pieces and says so. 400 cells went in, the board (not over) holds 0..100 of them: 30 <= lines <= 40.
    rules = TetrisRules(width=10, height=10)
    lines, pieces, capped = play(
        rules, DELLACHERIE, torch.tensor(DELLACHERIE_WEIGHTS), torch.arange(6), max_pieces=100
    )
    assert capped.all()
    assert pieces.tolist() == [100] * 6
    assert ((lines >= 30) & (lines <= 40)).all()


def test_play_matches_stepping_the_engine():
    # play() (whole games in one kernel) and afterstates() + step() agree: the greedy linear policy takes
    # the first best placement and a game-ending one only when nothing else is left.
    rules = TetrisRules(width=8, height=8)
    w = np.array(DELLACHERIE_WEIGHTS)
    seeds = torch.tensor([3, 4, 5])
    lines, pieces, _ = play(rules, DELLACHERIE, torch.from_numpy(w), seeds)
    eng = NumbaEngine(rules, 3, DELLACHERIE)
    eng.reset(torch.ones(3, dtype=torch.bool), seeds)
    total = np.zeros(3, np.int64)
    count = np.zeros(3, np.int64)
    while eng.alive.any():
        feats, mask, terminal, _ = eng.afterstates()
        values = feats.double().numpy() @ w + np.where(terminal.numpy(), -1.0e30, 0.0)
        values[~mask.numpy()] = -np.inf
        count += eng.alive
        total += eng.step(torch.from_numpy(values.argmax(1))).numpy()
    assert total.tolist() == lines.tolist()
    assert count.tolist() == pieces.tolist()
    assert (lines > 0).all()
