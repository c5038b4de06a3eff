"""The torch engine reproduces the numba engine exactly: afterstates, steps, whole games."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.envs.tetris import engine_numba, engine_torch
from hfrl_torch.envs.tetris.engine_numba import NumbaEngine
from hfrl_torch.envs.tetris.engine_torch import TorchEngine
from hfrl_torch.envs.tetris.features import BT, DELLACHERIE, DELLACHERIE_WEIGHTS, DT, KNOX, feature_size
from hfrl_torch.envs.tetris.rules import TetrisRules

DEVICES = [
    "cpu",
    pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")),
]
SIZES = [(10, 20), (6, 8), (4, 4)]
FIDS = [BT, KNOX, DELLACHERIE, DT]


def _drive(rules: TetrisRules, fid: int, seed: int, steps: int, batch: int, device: str = "cpu") -> None:
    """Play both engines with the same random placements, asserting identical outputs at every step."""
    ne = NumbaEngine(rules, batch, fid)
    te = TorchEngine(rules, batch, fid, device)
    rng = np.random.default_rng(seed)
    seeds = torch.as_tensor(rng.integers(0, 2**62, batch), dtype=torch.int64)
    every = torch.ones(batch, dtype=torch.bool)
    ne.reset(every, seeds)
    te.reset(every, seeds)
    for t in range(steps):
        for x, y in zip(ne.afterstates(), te.afterstates(), strict=True):
            assert torch.equal(x, y.cpu()), (rules, fid, t)
        assert torch.equal(ne.board_features(), te.board_features().cpu())
        assert torch.equal(ne.next_pieces(), te.next_pieces().cpu())
        n_act = torch.as_tensor(ne.table.num_actions)[ne.state_tensors()["pieces"]]
        actions = (torch.as_tensor(rng.random(batch)) * n_act).long()
        assert torch.equal(ne.step(actions), te.step(actions.to(device)).cpu())
        s1, s2 = ne.state_tensors(), te.state_tensors()
        for k in s1:
            assert torch.equal(s1[k], s2[k].cpu()), (k, t)
        assert torch.equal(ne.boards(), te.boards().cpu())
        if t % 5 != 4:
            continue  # finished boards stay finished for a while: their outputs must match too
        dead = ~s1["alive"]
        restart = torch.as_tensor(rng.integers(0, 2**62, batch), dtype=torch.int64)
        ne.reset(dead, restart)
        te.reset(dead.to(device), restart.to(device))


@pytest.mark.parametrize("fid", FIDS)
@pytest.mark.parametrize(("width", "height"), SIZES)
def test_afterstates_and_steps_match_numba(width: int, height: int, fid: int) -> None:
    _drive(TetrisRules(width=width, height=height), fid, seed=width * 31 + height + fid, steps=25, batch=24)


@pytest.mark.parametrize("fid", FIDS)
def test_options_match_numba(fid: int) -> None:
    rules = TetrisRules(width=6, height=8, bag=True, spawn_topout=True)
    _drive(rules, fid, seed=fid, steps=25, batch=24)


@pytest.mark.parametrize("device", DEVICES)
def test_device_matches_numba(device: str) -> None:
    _drive(TetrisRules(width=6, height=10), DT, seed=5, steps=10, batch=16, device=device)


@settings(deadline=None, max_examples=12, derandomize=True)
@given(
    seed=st.integers(0, 2**31),
    steps=st.integers(0, 30),
    size=st.sampled_from(SIZES),
    fid=st.sampled_from(FIDS),
)
def test_property_random_boards_match(seed: int, steps: int, size: tuple[int, int], fid: int) -> None:
    _drive(TetrisRules(width=size[0], height=size[1]), fid, seed=seed, steps=steps, batch=8)


def _expected_from_cells(cells: np.ndarray) -> dict[str, np.ndarray]:
    """Heights, holes and transitions of boards [B, H, W] computed cell by cell."""
    b, h, w = cells.shape
    rows = np.arange(1, h + 1)[None, :, None]
    heights = (cells * rows).max(axis=1)
    holes = (~cells & (rows <= heights[:, None, :])).sum(axis=(1, 2))
    walled = np.concatenate([np.ones((b, h, 1), bool), cells, np.ones((b, h, 1), bool)], axis=2)
    row_tr = (walled[:, :, 1:] != walled[:, :, :-1]).sum(axis=(1, 2))
    floored = np.concatenate([np.ones((b, 1, w), bool), cells], axis=1)
    col_tr = (floored[:, 1:] != floored[:, :-1]).sum(axis=(1, 2))
    return {"heights": heights, "holes": holes, "row_tr": row_tr, "col_tr": col_tr}


@settings(deadline=None, max_examples=15, derandomize=True)
@given(seed=st.integers(0, 2**31), steps=st.integers(1, 40), size=st.sampled_from(SIZES))
def test_property_features_consistent_with_cells(seed: int, steps: int, size: tuple[int, int]) -> None:
    rules = TetrisRules(width=size[0], height=size[1])
    batch = 8
    bt = TorchEngine(rules, batch, BT)
    dell = TorchEngine(rules, batch, DELLACHERIE)
    rng = np.random.default_rng(seed)
    seeds = torch.as_tensor(rng.integers(0, 2**62, batch), dtype=torch.int64)
    bt.reset(torch.ones(batch, dtype=torch.bool), seeds)
    dell.reset(torch.ones(batch, dtype=torch.bool), seeds)
    for _ in range(steps):
        n_act = torch.as_tensor(bt.table.num_actions)[bt.pieces]
        actions = (torch.as_tensor(rng.random(batch)) * n_act).long()
        bt.step(actions)
        dell.step(actions)
    live = bt.alive.numpy()
    exp = _expected_from_cells(bt.boards().numpy())
    f_bt = bt.board_features().numpy()
    f_dell = dell.board_features().numpy()
    w = rules.width
    np.testing.assert_array_equal(f_bt[live, :w], exp["heights"][live])
    np.testing.assert_array_equal(bt.heights.numpy()[live], exp["heights"][live])
    np.testing.assert_array_equal(f_bt[live, 2 * w], exp["holes"][live])
    np.testing.assert_array_equal(f_dell[live, 2], exp["row_tr"][live])
    np.testing.assert_array_equal(f_dell[live, 3], exp["col_tr"][live])
    np.testing.assert_array_equal(f_dell[live, 4], exp["holes"][live])


def _play_both(
    rules: TetrisRules, fid: int, weights: torch.Tensor, seeds: torch.Tensor, **kw: object
) -> None:
    a = engine_numba.play(rules, fid, weights, seeds, **kw)
    b = engine_torch.play(rules, fid, weights, seeds, chunk=4, **kw)
    for x, y, name in zip(a, b, ("lines", "pieces", "capped"), strict=True):
        assert torch.equal(x, y), (name, x, y)


def test_play_dellacherie_matches_numba() -> None:
    w = torch.tensor(DELLACHERIE_WEIGHTS)
    seeds = torch.arange(6, dtype=torch.int64)
    _play_both(TetrisRules(width=10, height=10), DELLACHERIE, w, seeds, max_pieces=250)
    lines, pieces, capped = engine_torch.play(
        TetrisRules(width=10, height=10), DELLACHERIE, w, seeds, max_pieces=250
    )
    assert capped.any() and (pieces <= 250).all() and (lines > 0).all()


def test_play_full_games_match_numba() -> None:
    rules = TetrisRules(width=6, height=8)
    g = torch.Generator().manual_seed(3)
    weights = torch.randint(-5, 6, (10, feature_size(DT, 6)), generator=g).to(torch.float64)
    _play_both(rules, DT, weights, torch.arange(10, dtype=torch.int64) + 100)
    # a policy that loves height: only the terminal penalty keeps it from ending the game early
    _play_both(rules, BT, torch.ones(feature_size(BT, 6)), torch.arange(10, dtype=torch.int64))


@pytest.mark.parametrize(
    "rules",
    [TetrisRules(width=10, height=10), TetrisRules(width=6, height=8, bag=True, spawn_topout=True)],
)
def test_play_random_policy_matches_numba(rules: TetrisRules) -> None:
    seeds = torch.arange(16, dtype=torch.int64)
    zeros = torch.zeros(feature_size(BT, rules.width))
    _play_both(rules, BT, zeros, seeds, random_policy=True, policy_seeds=seeds * 7 + 1)


def test_play_bag_topout_and_cap_match_numba() -> None:
    rules = TetrisRules(width=8, height=10, bag=True, spawn_topout=True)
    g = torch.Generator().manual_seed(0)
    weights = torch.randn(8, feature_size(KNOX, 8), generator=g, dtype=torch.float64)
    _play_both(rules, KNOX, weights, torch.arange(8, dtype=torch.int64), max_pieces=60)
    _play_both(rules, DELLACHERIE, torch.tensor(DELLACHERIE_WEIGHTS), torch.arange(4), max_pieces=120)
