"""Rules of the numba Tetris engine, checked against values worked out by hand.

Boards are written as pictures, top row first, ``X`` = filled; the last line of a
picture is row 0 (the bottom). Piece shapes are pictures too, so that a reader can
check every expected value without knowing the engine's orientation numbering.
Reference: /work/shared/specs/tetris.md ("simplified" rules).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hfrl_torch.envs.tetris.engine_numba import SPARE_ROWS, NumbaEngine
from hfrl_torch.envs.tetris.features import BT
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, orientations, placement_table
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.envs.tetris.sequence import game_key, game_key_t, piece_at, piece_at_t

# ---------------------------------------------------------------- helpers


def parse_board(picture: list[str], width: int) -> tuple[list[int], list[int]]:
    """(row bitmasks with row 0 first, column heights) of a picture given top row first."""
    assert all(len(line) == width for line in picture), picture
    rows = [sum(1 << c for c, ch in enumerate(line) if ch == "X") for line in reversed(picture)]
    heights = [max((r + 1 for r, row in enumerate(rows) if row >> c & 1), default=0) for c in range(width)]
    return rows, heights


def shape_cells(shape: str) -> tuple[tuple[int, int], ...]:
    """Cells (row from the bottom, col) of a shape like ``".X./XXX"`` (top row first)."""
    lines = shape.split("/")
    cells = [
        (len(lines) - 1 - i, c) for i, line in enumerate(lines) for c, ch in enumerate(line) if ch == "X"
    ]
    return tuple(sorted(cells))


def action(width: int, piece: str, shape: str, col: int) -> int:
    """Placement index of ``piece`` in orientation ``shape`` with its leftmost cell in column ``col``."""
    table = placement_table(width)
    p = PIECE_NAMES.index(piece)
    o = orientations(piece).index(shape_cells(shape))
    for a in range(int(table.num_actions[p])):
        if table.orient[p, a] == o and table.column[p, a] == col:
            return a
    raise AssertionError(f"no placement {piece} {shape} at column {col}")


def make_engine(width: int, height: int, batch: int = 1, fid: int = BT, **options: bool) -> NumbaEngine:
    eng = NumbaEngine(TetrisRules(width=width, height=height, **options), batch, fid)
    eng.reset(torch.ones(batch, dtype=torch.bool), torch.arange(batch, dtype=torch.int64))
    return eng


def set_board(eng: NumbaEngine, picture: list[str], piece: str, b: int = 0) -> None:
    rows, heights = parse_board(picture, eng.rules.width)
    eng.rows[b] = 0
    eng.rows[b, : len(rows)] = rows
    eng.heights[b] = heights
    eng.pieces[b] = PIECE_NAMES.index(piece)


def picture_of(eng: NumbaEngine, b: int = 0, nrows: int | None = None) -> list[str]:
    """Picture (top first) of the lowest ``nrows`` rows of board b, spare rows included."""
    n = nrows if nrows is not None else eng.rules.height
    w = eng.rules.width
    return ["".join("X" if eng.rows[b, r] >> c & 1 else "." for c in range(w)) for r in reversed(range(n))]


def drop(eng: NumbaEngine, a: int) -> int:
    """Place the current piece of board 0 with placement ``a``; returns lines cleared."""
    return int(eng.step(torch.tensor([a], dtype=torch.int64))[0])


# ---------------------------------------------------------------- placements


def test_distinct_orientations():
    # I 2, O 1, S 2, Z 2, T/L/J 4 (spec, "only distinct orientations count")
    counts = {name: len(orientations(name)) for name in PIECE_NAMES}
    assert counts == {"I": 2, "O": 1, "T": 4, "S": 2, "Z": 2, "L": 4, "J": 4}


@pytest.mark.parametrize(
    ("width", "expected"),
    [
        # A piece w columns wide has width - w + 1 columns to go to.
        # I: flat (4 wide) + upright (1 wide) = (W-3) + W; O: W-1; S, Z: (W-2) + (W-1);
        # T, L, J: two 3-wide and two 2-wide orientations = 2(W-2) + 2(W-1).
        (10, {"I": 7 + 10, "O": 9, "T": 16 + 18, "S": 8 + 9, "Z": 8 + 9, "L": 34, "J": 34}),
        (6, {"I": 3 + 6, "O": 5, "T": 8 + 10, "S": 4 + 5, "Z": 4 + 5, "L": 18, "J": 18}),
        (4, {"I": 1 + 4, "O": 3, "T": 4 + 6, "S": 2 + 3, "Z": 2 + 3, "L": 10, "J": 10}),
    ],
)
def test_placement_counts(width, expected):
    assert expected["I"] == {10: 17, 6: 9, 4: 5}[width]  # the spec's 17 / 9 / 17 / 34 on 10 wide
    table = placement_table(width)
    got = {name: int(table.num_actions[p]) for p, name in enumerate(PIECE_NAMES)}
    assert got == expected
    assert table.max_actions == max(expected.values())
    # the engine offers exactly that many valid afterstates on an empty board
    eng = make_engine(width, 8, batch=7)
    eng.pieces[:] = np.arange(7)
    _, mask, terminal, lines = eng.afterstates()
    assert mask.sum(1).tolist() == [expected[n] for n in PIECE_NAMES]
    assert not terminal.any()
    # nothing clears on an empty board, except the flat I on a 4-wide board (placement 0), which fills row 0
    assert lines.sum().item() == (1 if width == 4 else 0)
    assert lines[0, 0].item() == (1 if width == 4 else 0)


def test_landing_positions_on_stepped_surface():
    # heights 4 3 2 1 0 0 1 2 0 0; a piece stops on the highest support under any of its columns:
    # landing row = max over the piece's columns of (column height - lowest piece cell in that column)
    surface = [
        "X.........",
        "XX........",
        "XXX....X..",
        "XXXX..XX..",
    ]
    base = [4, 3, 2, 1, 0, 0, 1, 2, 0, 0]
    cases = [
        # (piece, shape, col, new heights of the columns it covers, holes it leaves under itself)
        # O: land max(4,3)=4; column 1 (height 3) gets a hole at row 3
        ("O", "XX/XX", 0, {0: 6, 1: 6}, 1),
        # T flat: land max(3,2,1)=3; holes col 2 row 2, col 3 rows 1-2
        ("T", ".X./XXX", 1, {1: 4, 2: 5, 3: 4}, 3),
        # T pointing down, lowest cells (1,0,1): land max(2-1,1-0,0-1)=1; col 4 holes rows 0-1
        ("T", "XXX/.X.", 2, {2: 3, 3: 3, 4: 3}, 2),
        # S flat, lowest cells (0,0,1): land max(1,0,-1)=1; holes col 4 row 0, col 5 rows 0-1
        ("S", ".XX/XX.", 3, {3: 2, 4: 3, 5: 3}, 3),
        # Z flat, lowest cells (1,0,0): land max(-1,1,2)=2; holes col 5 rows 0-2, col 6 row 1
        ("Z", "XX./.XX", 5, {5: 4, 6: 4, 7: 3}, 4),
        # upright I on the floor
        ("I", "X/X/X/X", 8, {8: 4}, 0),
        # L flat: land 2 (column 7); holes cols 8, 9 rows 0-1
        ("L", "..X/XXX", 7, {7: 3, 8: 3, 9: 4}, 4),
        # J upright with its hook over column 6, lowest cells (0,2): land max(0,1-2)=0; hole col 6 row 1
        ("J", "XX/X./X.", 5, {5: 3, 6: 3}, 1),
        # flat I: land max(1,0,0,1)=1; holes cols 4, 5 row 0
        ("I", "XXXX", 3, {3: 2, 4: 2, 5: 2, 6: 2}, 2),
        # S upright, lowest cells (1,0): land max(2-1,1-0)=1, fits the step exactly
        ("S", "X./XX/.X", 2, {2: 4, 3: 3}, 0),
    ]
    eng = make_engine(10, 10)
    for piece, shape, col, changed, holes in cases:
        set_board(eng, surface, piece)
        feats, mask, terminal, lines = eng.afterstates()
        a = action(10, piece, shape, col)
        expected = list(base)
        for c, h in changed.items():
            expected[c] = h
        assert mask[0, a] and not terminal[0, a] and lines[0, a] == 0
        assert feats[0, a, :10].tolist() == expected, (piece, shape, col)
        assert feats[0, a, 20].item() == holes, (piece, shape, col)
    # the same through step(): J upright at column 5 leaves a hole under its overhang in column 6
    set_board(eng, surface, "J")
    assert drop(eng, action(10, "J", "XX/X./X.", 5)) == 0
    assert picture_of(eng, nrows=4) == [
        "X.........",
        "XX...XX...",
        "XXX..X.X..",
        "XXXX.XXX..",
    ]
    assert eng.heights[0].tolist() == [4, 3, 2, 1, 0, 3, 3, 2, 0, 0]


# ---------------------------------------------------------------- line clears


def test_clear_one_line_rows_above_move_down():
    # row 0 has columns 0..5; a flat I in columns 6..9 completes it. The cell of row 1 (column 0)
    # drops to row 0.
    eng = make_engine(10, 6)
    set_board(eng, ["X.........", "XXXXXX...."], "I")
    assert drop(eng, action(10, "I", "XXXX", 6)) == 1
    assert picture_of(eng, nrows=2) == ["..........", "X........."]
    assert eng.heights[0].tolist() == [1, 0, 0, 0, 0, 0, 0, 0, 0, 0]
    assert eng.alive[0]


def test_clear_two_lines():
    # rows 0, 1 miss columns 8, 9; an O there completes both; the lone cell of row 2 (column 3) drops to row 0
    eng = make_engine(10, 6)
    set_board(eng, ["...X......", "XXXXXXXX..", "XXXXXXXX.."], "O")
    assert drop(eng, action(10, "O", "XX/XX", 8)) == 2
    assert picture_of(eng, nrows=2) == ["..........", "...X......"]
    assert eng.heights[0].tolist() == [0, 0, 0, 1, 0, 0, 0, 0, 0, 0]


def test_clear_three_lines_piece_remainder_moves_down():
    # rows 0..2 miss column 9; row 3 holds column 0. An upright I in column 9 fills rows 0..3:
    # rows 0..2 clear, row 3 (columns 0 and 9) becomes row 0.
    eng = make_engine(10, 6)
    set_board(eng, ["X.........", "XXXXXXXXX.", "XXXXXXXXX.", "XXXXXXXXX."], "I")
    assert drop(eng, action(10, "I", "X/X/X/X", 9)) == 3
    assert picture_of(eng, nrows=2) == ["..........", "X........X"]
    assert eng.heights[0].tolist() == [1, 0, 0, 0, 0, 0, 0, 0, 0, 1]


def test_clear_four_lines_with_hole_below():
    # a 4-deep well in column 9 over a floor cell at row 0; column 2 has a hole at row 0 under the four rows.
    # The upright I lands at row 1 (column 9 height 1) and clears rows 1..4. Row 0 is left; column 2's
    # height drops from 5 to 0 (its only cells were in the cleared rows), every other column to 1.
    eng = make_engine(10, 8)
    well = ["XXXXXXXXX."] * 4 + ["XX.XXXXXXX"]
    set_board(eng, well, "I")
    assert eng.heights[0].tolist() == [5, 5, 5, 5, 5, 5, 5, 5, 5, 1]
    _, _, terminal, lines = eng.afterstates()
    a = action(10, "I", "X/X/X/X", 9)
    assert lines[0, a] == 4 and not terminal[0, a]
    assert drop(eng, a) == 4
    assert picture_of(eng, nrows=2) == ["..........", "XX.XXXXXXX"]
    assert eng.heights[0].tolist() == [1, 1, 0, 1, 1, 1, 1, 1, 1, 1]


def test_clear_two_non_adjacent_lines():
    # rows 0 and 2 miss only column 9; rows 1 and 3 also miss column 0 (column 0: cells at rows 0, 2 only).
    # The upright I fills column 9 rows 0..3: rows 0 and 2 clear, rows 1 and 3 (columns 1..9) become
    # rows 0 and 1. Column 0 ends empty (height 0), the others at 2.
    eng = make_engine(10, 6)
    set_board(eng, [".XXXXXXXX.", "XXXXXXXXX.", ".XXXXXXXX.", "XXXXXXXXX."], "I")
    assert drop(eng, action(10, "I", "X/X/X/X", 9)) == 2
    assert picture_of(eng, nrows=3) == ["..........", ".XXXXXXXXX", ".XXXXXXXXX"]
    assert eng.heights[0].tolist() == [0] + [2] * 9


# ---------------------------------------------------------------- game over


def test_piece_ending_above_the_top_is_game_over():
    # 10 x 4: column 0 is full to the top (height 4 = H is still legal). A flat I on columns 0..3 lands on
    # row 4, above the board, clears nothing: game over. A flat I on columns 6..9 stays inside.
    eng = make_engine(10, 4)
    set_board(eng, ["X........."] * 4, "I")
    _, mask, terminal, lines = eng.afterstates()
    assert terminal[0, action(10, "I", "XXXX", 0)] and lines[0, action(10, "I", "XXXX", 0)] == 0
    assert not terminal[0, action(10, "I", "XXXX", 6)]
    # only the two placements covering column 0 (flat at column 0, upright at column 0) end the game
    assert int(terminal[0, : int(mask[0].sum())].sum()) == 2
    # upright I on column 1 (height 0) reaches row 3 only: inside
    assert not terminal[0, action(10, "I", "X/X/X/X", 1)]
    drop(eng, action(10, "I", "XXXX", 0))
    assert not eng.alive[0]
    assert eng.heights[0].tolist() == [5, 5, 5, 5, 0, 0, 0, 0, 0, 0]


def test_piece_sticking_out_that_clears_back_inside_is_not_game_over():
    # 4 x 4 (column 2 has a hole at row 0, column 3 height 1):
    #   XXX.      row 3
    #   XXX.      row 2
    #   XXX.      row 1
    #   XX.X      row 0
    # An upright I in column 3 lands on row 1 and occupies rows 1..4: row 4 is above the top (H = 4).
    # Rows 1..3 become full and clear; the I's cell on row 4 drops to row 1, inside the board.
    eng = make_engine(4, 4)
    set_board(eng, ["XXX.", "XXX.", "XXX.", "XX.X"], "I")
    a = action(4, "I", "X/X/X/X", 3)
    _, _, terminal, lines = eng.afterstates()
    assert lines[0, a] == 3 and not terminal[0, a]
    assert drop(eng, a) == 3
    assert eng.alive[0]
    assert picture_of(eng) == ["....", "....", "...X", "XX.X"]
    assert eng.heights[0].tolist() == [1, 1, 0, 2]


def test_piece_sticking_out_still_outside_after_clearing_is_game_over():
    # 4 x 4:
    #   XX..      row 3
    #   XXX.      row 2
    #   XX.X      row 1
    #   XXX.      row 0
    # Upright I in column 3 (height 2) occupies rows 2..5; only row 2 is full. After it clears, the I's
    # cells are at rows 1 (old), 2, 3, 4: column 3's height is 5 > 4, game over (1 line still counted).
    # Columns 0, 1 lose row 2 (height 4 -> 3), column 2 keeps row 0 only (height 3 -> 1).
    eng = make_engine(4, 4)
    set_board(eng, ["XX..", "XXX.", "XX.X", "XXX."], "I")
    a = action(4, "I", "X/X/X/X", 3)
    _, _, terminal, lines = eng.afterstates()
    assert lines[0, a] == 1 and terminal[0, a]
    assert drop(eng, a) == 1
    assert not eng.alive[0]
    assert eng.heights[0].tolist() == [3, 3, 1, 5]
    assert picture_of(eng, nrows=4 + SPARE_ROWS) == [
        "....",
        "....",
        "....",
        "...X",
        "...X",
        "XX.X",
        "XX.X",
        "XXX.",
    ]


@pytest.mark.parametrize("spawn_topout", [False, True])
def test_spawn_zone_topout(spawn_topout):
    # 10 x 6, column 4 filled on rows 0..4 (height 5 = H - 1). The next piece spawns in its first orientation
    # at the top centre (left column (10 - piece width) // 2), its top on row 5. Only the flat I (one row,
    # row 5) fits; every other piece has a cell on row 4 in column 4 (O: cols 4,5; T, L, J: cols 3..5;
    # S: cols 3,4; Z: cols 4,5). With the option, the game ends exactly when the next piece is not an I.
    n = 60
    eng = make_engine(10, 6, batch=n, spawn_topout=spawn_topout)
    for b in range(n):
        set_board(eng, ["....X....."] * 5, "O", b)
    nxt = eng.next_pieces()
    eng.step(torch.full((n,), action(10, "O", "XX/XX", 0), dtype=torch.int64))
    assert eng.pieces.tolist() == nxt.tolist()
    is_i = (nxt == PIECE_NAMES.index("I")).numpy()
    assert 0 < is_i.sum() < n  # both cases occur among these seeds
    if spawn_topout:
        assert (eng.alive == is_i).all()
    else:
        assert eng.alive.all()


# ---------------------------------------------------------------- piece sequences


def sequence(seed: int, n: int, bag: bool = False) -> list[int]:
    key = game_key(seed)
    return [piece_at(key, i, bag) for i in range(n)]


def test_piece_sequence_is_a_function_of_the_seed():
    assert sequence(123, 200) == sequence(123, 200)
    seqs = [tuple(sequence(s, 40)) for s in range(50)]
    assert len(set(seqs)) == 50  # 50 seeds, 50 different games
    # large seeds (beyond 32 bits) are distinct games too
    assert sequence(1 << 40, 40) != sequence(0, 40)
    # i.i.d. uniform: 14,000 draws, each piece 2000 +- 200 (sd about 41)
    draws = np.array([p for s in range(100) for p in sequence(s, 140)])
    counts = np.bincount(draws, minlength=7)
    assert counts.sum() == 14000 and (np.abs(counts - 2000) < 200).all(), counts


def test_engine_pieces_follow_the_seed_not_the_actions():
    # two engines, same seeds, different moves: the same piece sequences, equal to piece_at(seed, i)
    seeds = torch.tensor([7, 8, 9], dtype=torch.int64)
    runs = []
    for first in (True, False):
        eng = NumbaEngine(TetrisRules(width=10, height=100), 3, BT)
        eng.reset(torch.ones(3, dtype=torch.bool), seeds)
        got = []
        for _ in range(20):
            got.append(eng.pieces.copy())
            acts = [0 if first else int(eng.table.num_actions[p]) - 1 for p in eng.pieces]
            eng.step(torch.tensor(acts, dtype=torch.int64))
        assert eng.alive.all()
        runs.append(np.stack(got, 1))
    assert (runs[0] == runs[1]).all()
    for b, s in enumerate(seeds.tolist()):
        assert runs[0][b].tolist() == sequence(s, 20)
    # resetting with the same seed restarts the same game
    eng = NumbaEngine(TetrisRules(width=10, height=60), 3, BT)
    eng.reset(torch.ones(3, dtype=torch.bool), seeds)
    assert eng.pieces.tolist() == runs[0][:, 0].tolist()


def test_seven_bag_gives_each_piece_once_per_bag():
    for seed in range(20):
        seq = sequence(seed, 7 * 30, bag=True)
        for j in range(30):
            assert sorted(seq[7 * j : 7 * j + 7]) == list(range(7)), (seed, j)
        assert len({tuple(seq[7 * j : 7 * j + 7]) for j in range(30)}) > 20  # bags are shuffled anew
    assert sequence(1, 70, bag=True) != sequence(2, 70, bag=True)
    # through the engine
    eng = make_engine(10, 60, bag=True)
    got = []
    for _ in range(14):
        got.append(int(eng.pieces[0]))
        eng.step(torch.tensor([0], dtype=torch.int64))
    assert sorted(got[:7]) == list(range(7)) and sorted(got[7:]) == list(range(7))


@pytest.mark.parametrize("bag", [False, True])
def test_torch_sequence_twin_matches(bag):
    seeds = torch.tensor([0, 1, 2, 12345, (1 << 40) + 3, (1 << 62) - 1], dtype=torch.int64)
    idx = torch.arange(50, dtype=torch.int64)
    keys = game_key_t(seeds)
    assert keys.tolist() == [game_key(int(s)) for s in seeds]
    got = piece_at_t(keys[:, None].expand(-1, 50), idx[None, :].expand(len(seeds), -1), bag)
    want = [[piece_at(game_key(int(s)), i, bag) for i in range(50)] for s in seeds]
    assert got.tolist() == want
