"""Hashed one-dimensional tile coding: widths, hand-computed tile coordinates, hashing, sparse reads and
updates over a learner batch."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.models.tile_coding import TileCoding, hash_tiles, keepaway_tile_widths, tile_coordinates


def test_keepaway_widths_are_the_spec_values():
    assert keepaway_tile_widths(3, 2) == [2, 2, 3, 2, 3, 2, 3, 3, 3, 4, 4, 10, 10]
    assert len(keepaway_tile_widths(4, 3)) == 4 * 4 + 2 * 3 - 3
    with pytest.raises(ValueError):
        keepaway_tile_widths(2, 1)


def test_coordinates_four_tilings_by_hand():
    # width 2, T = 4: q = floor(value / 2 * 4); tiling j holds tile floor((q - j) / 4), so tiling j's
    # boundaries lie at (j / 4 + k) widths.
    widths = torch.tensor([2.0])
    coords = tile_coordinates(torch.tensor([[1.0], [-1.0], [3.9], [4.0], [0.0]]), widths, 4)
    assert coords.shape == (5, 1, 4)
    assert coords[:, 0].tolist() == [
        [0, 0, 0, -1],  # x = 0.5, q = 2
        [-1, -1, -1, -2],  # x = -0.5, q = -2: floor, not truncation
        [1, 1, 1, 1],  # x = 1.95, q = 7
        [2, 1, 1, 1],  # x = 2.0, q = 8: only tiling 0 has a boundary at 2 widths
        [0, -1, -1, -1],  # x = 0, q = 0
    ]


def test_coordinates_thirty_two_tilings_by_hand():
    widths = torch.tensor(keepaway_tile_widths(3, 2))
    values = torch.zeros(2, 13)
    values[0, 0] = 5.3  # width 2: x = 2.65, q = 84 -> tilings 0..20 in tile 2, 21..31 in tile 1
    values[1, 2] = -0.3  # width 3: x = -0.1, q = -4 -> tilings 0..28 in tile -1, 29..31 in tile -2
    values[1, 12] = 95.0  # width 10 (degrees): x = 9.5, q = 304 -> tilings 0..16 in tile 9, 17..31 in 8
    coords = tile_coordinates(values, widths, 32)
    assert coords.shape == (2, 13, 32)
    assert coords[0, 0].tolist() == [2] * 21 + [1] * 11
    assert coords[1, 2].tolist() == [-1] * 29 + [-2] * 3
    assert coords[1, 12].tolist() == [9] * 17 + [8] * 15
    assert coords[0, 1].tolist() == [0] + [-1] * 31  # value 0


@pytest.mark.parametrize("size", [1, 7, 1000, 2**20, 2**30])
def test_hash_stays_in_range(size):
    gen = torch.Generator().manual_seed(0)
    coords = torch.randint(-(10**9), 10**9, (64, 13, 32), generator=gen)
    coords[0] = -(2**40)
    coords[1] = 2**40
    index = hash_tiles(coords, 3, size)
    assert index.shape == (64, 3, 13 * 32)
    assert index.dtype == torch.int64
    assert int(index.min()) >= 0 and int(index.max()) < size


def test_hash_is_a_function_of_action_variable_tiling_and_coordinate():
    coords = torch.zeros(1, 13, 32, dtype=torch.int64)
    a = hash_tiles(coords, 3, 2**20)
    assert torch.equal(a, hash_tiles(coords.clone(), 3, 2**20))  # deterministic
    # every (action, variable, tiling) is its own tile even at the same coordinate: few collisions
    assert a.unique().numel() >= 0.99 * a.numel()
    shifted = hash_tiles(coords + 1, 3, 2**20)
    assert (shifted != a).float().mean() > 0.99
    with pytest.raises(ValueError):
        hash_tiles(coords, 3, 2**31)


def test_tiles_per_action_and_spread():
    coder = TileCoding(keepaway_tile_widths(3, 2), num_actions=3, learners=2)
    assert coder.active_tiles == 416
    gen = torch.Generator().manual_seed(1)
    tiles = coder.tiles(torch.rand(100, 13, generator=gen) * 20)
    assert tiles.shape == (100, 3, 416)
    assert int(tiles.min()) >= 0 and int(tiles.max()) < 2**20
    within = torch.tensor([row.unique().numel() for row in tiles.reshape(100, -1)], dtype=torch.float64)
    assert within.mean() > 0.995 * 3 * 416  # collisions inside one state's 1248 tiles are rare


def test_sparse_read_and_update_per_learner():
    coder = TileCoding([1.0, 2.0], num_actions=2, learners=3, tilings=2, size=64, dtype=torch.float64)
    assert not coder.weight.requires_grad
    tiles = coder.tiles(torch.tensor([[0.3, 0.3], [0.3, 0.3]]))  # [2, 2, 4]
    learners = torch.tensor([2, 0])
    coder.add_(learners, tiles[:, 1], torch.tensor([[1.0, 2.0, 3.0, 4.0], [0.5, 0.5, 0.5, 0.5]]))
    assert tiles[0, 1].unique().numel() == 4  # no collision among the four tiles of action 1
    q = coder(learners, tiles)
    assert q[:, 1].tolist() == [1.0 + 2.0 + 3.0 + 4.0, 4 * 0.5]
    assert coder.weight[1].abs().sum() == 0  # learner 1 untouched
    assert int((coder.weight != 0).sum()) == 8  # only the touched entries changed
    # repeated indices add up (index_add_), as a tile that appears twice in F_a does
    coder.add_(torch.tensor([1]), torch.tensor([[5, 5]]), torch.tensor([[1.0, 2.0]]))
    assert coder.weight[1, 5] == 3.0


def test_learner_batch_matches_separate_coders():
    gen = torch.Generator().manual_seed(2)
    obs = torch.rand(4, 13, generator=gen) * 15
    big = TileCoding(keepaway_tile_widths(), 3, learners=4, size=2**12)
    tiles = big.tiles(obs)
    values = torch.rand(4, 416, generator=gen)
    big.add_(torch.arange(4), tiles[:, 0], values)
    for i in range(4):
        one = TileCoding(keepaway_tile_widths(), 3, learners=1, size=2**12)
        one.add_(torch.tensor([0]), tiles[i : i + 1, 0], values[i : i + 1])
        assert torch.equal(one.weight[0], big.weight[i])
        assert torch.allclose(
            one(torch.tensor([0]), tiles[i : i + 1]), big(torch.tensor([i]), tiles[i : i + 1])
        )
