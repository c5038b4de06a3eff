"""Primitive-move Tetris: walls, rotation, gravity, hard drop vs placements, line clears, top-out."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from hfrl_torch.envs.tetris.engine_torch import TorchEngine
from hfrl_torch.envs.tetris.features import BT
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, orientations, rotation_cycle
from hfrl_torch.envs.tetris.primitive import DROP, LEFT, RIGHT, ROTATE, PrimitiveTetris
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.envs.tetris.sequence import game_key, piece_at

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
]


def _seed_for(piece: int) -> int:
    """The first seed whose game starts with ``piece``."""
    return next(s for s in range(10_000) if piece_at(game_key(s), 0, False) == piece)


def _new(rules: TetrisRules, piece: int, device: str = "cpu") -> PrimitiveTetris:
    env = PrimitiveTetris(rules, 1, device)
    env.reset(torch.ones(1, dtype=torch.bool), torch.tensor([_seed_for(piece)]))
    return env


def _act(env: PrimitiveTetris, a: int) -> tuple[int, bool]:
    lines, locked = env.step(torch.tensor([a], device=env.device))
    return int(lines[0]), bool(locked[0])


def _shape(cells: torch.Tensor) -> tuple[tuple[int, int], ...]:
    rc = cells.nonzero().tolist()
    r0, c0 = min(r for r, _ in rc), min(c for _, c in rc)
    return tuple(sorted((r - r0, c - c0) for r, c in rc))


@pytest.mark.parametrize("device", DEVICES)
def test_moves_against_walls_are_ignored_and_gravity_pulls(device: str) -> None:
    env = _new(TetrisRules(width=10, height=30), PIECE_NAMES.index("O"), device)
    assert (int(env.col[0]), int(env.row[0])) == (4, 28)
    for k in range(6):
        _act(env, LEFT)
        assert int(env.col[0]) == max(4 - k - 1, 0)
        assert int(env.row[0]) == 28 - k - 1
    for _ in range(12):
        _act(env, RIGHT)
    assert int(env.col[0]) == 8
    assert int(env.row[0]) == 28 - 18
    cells = env.falling_cells()[0].cpu()
    assert cells[10:12, 8:10].all() and int(cells.sum()) == 4


def test_rotation_cycles_through_shapes_and_is_blocked_at_the_wall() -> None:
    for name in ("T", "L", "S", "I"):
        env = _new(TetrisRules(width=10, height=20), PIECE_NAMES.index(name))
        cycle = rotation_cycle(name)
        for k in range(1, 5):
            top = int(env.row[0]) + int(env._ph[env.pieces, env.rot][0]) - 1
            _act(env, ROTATE)
            assert int(env.rot[0]) == k % 4
            assert _shape(env.falling_cells()[0]) == cycle[k % 4]
            new_top = int(env.row[0]) + int(env._ph[env.pieces, env.rot][0]) - 1
            assert new_top == top - 1  # the rotation keeps the top; gravity then pulls one row
    env = _new(TetrisRules(width=10, height=20), PIECE_NAMES.index("I"))
    _act(env, ROTATE)
    for _ in range(8):
        _act(env, RIGHT)
    assert (int(env.rot[0]), int(env.col[0])) == (1, 9)
    _act(env, ROTATE)  # horizontal would leave the board: ignored
    assert int(env.rot[0]) == 1 and _shape(env.falling_cells()[0]) == rotation_cycle("I")[1]


def test_piece_locks_when_it_cannot_fall() -> None:
    env = _new(TetrisRules(width=6, height=8), PIECE_NAMES.index("O"))
    for k in range(6):
        lines, locked = _act(env, LEFT)
        assert not locked and int(env.row[0]) == 5 - k
    lines, locked = _act(env, LEFT)
    assert locked and lines == 0
    board = env.boards()[0]
    assert board[0:2, 0:2].all() and int(board.sum()) == 4
    assert int(env.index[0]) == 1 and bool(env.alive[0])


def test_hard_drop_equals_the_placement_engine() -> None:
    """Rotating to an orientation, moving to a column and dropping gives the placement's afterstate."""
    rules = TetrisRules(width=10, height=24)
    placed = 0
    for seed in range(8):
        eng = TorchEngine(rules, 1, BT)
        env = PrimitiveTetris(rules, 1)
        one, s = torch.ones(1, dtype=torch.bool), torch.tensor([seed])
        eng.reset(one, s)
        env.reset(one, s)
        rng = np.random.default_rng(seed)
        while bool(eng.alive[0]) and int(eng.heights.max()) <= 8:
            p = int(eng.pieces[0])
            assert p == int(env.pieces[0])
            a = int(rng.integers(eng.table.num_actions[p]))
            shape = orientations(PIECE_NAMES[p])[eng.table.orient[p, a]]
            k = rotation_cycle(PIECE_NAMES[p]).index(shape)
            for _ in range(k):
                assert not _act(env, ROTATE)[1]
            target = int(eng.table.column[p, a])
            while int(env.col[0]) != target:
                assert not _act(env, LEFT if int(env.col[0]) > target else RIGHT)[1]
            lines, locked = _act(env, DROP)
            assert locked and lines == int(eng.step(torch.tensor([a]))[0])
            assert torch.equal(env.boards(), eng.boards())
            placed += 1
    assert placed >= 40


def test_line_clear() -> None:
    rules = TetrisRules(width=10, height=8)
    env = _new(rules, PIECE_NAMES.index("O"))
    env.cells[0, 0:2, :] = True
    env.cells[0, 0:2, 4:6] = False
    env.cells[0, 2, 0] = True
    lines, locked = _act(env, DROP)
    assert locked and lines == 2
    board = env.boards()[0]
    assert bool(board[0, 0]) and int(board.sum()) == 1


def test_game_over_when_the_next_piece_cannot_spawn() -> None:
    rules = TetrisRules(width=10, height=8)
    env = _new(rules, PIECE_NAMES.index("O"))
    env.cells[0, 0:6, 4:6] = True
    lines, locked = _act(env, DROP)
    assert locked and lines == 0 and not bool(env.alive[0])
    assert not env.falling_cells().any()
    before = env.boards()
    lines, locked = _act(env, DROP)
    assert not locked and lines == 0 and torch.equal(env.boards(), before)
