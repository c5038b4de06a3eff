"""State variables on constructed scenes and the benchmark policies' choices."""

from __future__ import annotations

import math

import pytest
import torch

from hfrl_torch.envs.keepaway.policies import hand_coded_actions, hold_actions, random_actions
from hfrl_torch.envs.keepaway.state_vars import keeper_state_variables, quantised_view

T = torch.tensor


def _scene() -> tuple[torch.Tensor, torch.Tensor]:
    keepers = T([[[0.0, 0.0], [0.0, -8.0], [6.0, 0.0]]])
    takers = T([[[3.0, 4.0], [1.0, -1.0]]])
    return keepers, takers


def test_state_variables_of_a_constructed_scene() -> None:
    keepers, takers = _scene()
    state, order = keeper_state_variables(keepers, takers, T([0]))
    assert order.tolist() == [[2, 1]]  # K2 = keeper 2 (6 m), K3 = keeper 1 (8 m)
    expected = [
        0.0,  # dist(K1, C)
        6.0,
        8.0,  # dist(K1, K2), dist(K1, K3)
        math.sqrt(2),
        5.0,  # dist(K1, T1), dist(K1, T2); T1 = (1, -1)
        6.0,
        8.0,  # dist(K2, C), dist(K3, C)
        math.sqrt(2),
        5.0,  # dist(T1, C), dist(T2, C)
        5.0,
        math.hypot(1, 7),  # min dist to a taker: K2 -> (3, 4) = 5; K3 -> (1, -1)
        45.0,
        45.0,  # min angle at K1: K2 vs T1 (1,-1) = 45 deg; K3 (0,-8) vs T1 = 45 deg
    ]
    assert state[0].tolist() == pytest.approx(expected, abs=1e-4)


def test_state_vector_length_for_4v3_and_5v4() -> None:
    for n, m in ((4, 3), (5, 4)):
        gen = torch.Generator().manual_seed(0)
        keepers = torch.rand(2, n, 2, generator=gen) * 20 - 10
        takers = torch.rand(2, m, 2, generator=gen) * 20 - 10
        state, order = keeper_state_variables(keepers, takers, T([0, n - 1]))
        assert state.shape == (2, 4 * n + 2 * m - 3)
        assert order.shape == (2, n - 1)
        assert (order[1] != n - 1).all()


def test_hand_coded_holds_when_takers_are_far() -> None:
    keepers = T([[[0.0, 0.0], [5.0, 0.0], [0.0, 5.0]]])
    takers = T([[[5.5, 5.5], [-6.0, 0.0]]])
    state, _ = keeper_state_variables(keepers, takers, T([0]))
    assert hand_coded_actions(state, 3, 2).item() == 0


def test_hand_coded_passes_to_the_open_teammate() -> None:
    keepers = T([[[0.0, 0.0], [5.0, 0.0], [0.0, 9.0]]])
    takers = T([[[1.0, 0.5], [6.0, 0.5]]])  # both near the line to keeper 1 (x axis)
    state, order = keeper_state_variables(keepers, takers, T([0]))
    # K2 = keeper 1 (5 m): 4 * 1.118 + 5.7 deg < 90; K3 = keeper 2: 4 * 8.6 + 63 deg > 90
    assert order.tolist() == [[1, 2]]
    assert hand_coded_actions(state, 3, 2).item() == 2


def test_hand_coded_holds_when_no_pass_beats_90() -> None:
    keepers = T([[[0.0, 0.0], [5.0, 0.0], [-5.0, 0.0]]])
    takers = T([[[1.0, 0.2], [-1.0, 0.2]]])
    state, _ = keeper_state_variables(keepers, takers, T([0]))
    assert hand_coded_actions(state, 3, 2).item() == 0


def test_hold_and_random_policies() -> None:
    obs = torch.zeros(1000, 13)
    assert (hold_actions(obs) == 0).all()
    actions = random_actions(obs, 3, torch.Generator().manual_seed(0))
    counts = torch.bincount(actions, minlength=3)
    assert counts.min().item() > 250


def test_quantised_view_is_within_five_percent_and_one_degree() -> None:
    me, body = T([[0.0, 0.0]]), T([0.3])
    points = T([[[7.3, 2.1], [-3.0, 4.0], [0.5, -0.2]]])
    seen = quantised_view(me, body, points)
    true_d, seen_d = points[0].norm(dim=-1), seen[0].norm(dim=-1)
    assert ((seen_d - true_d).abs() <= 0.052 * true_d + 0.05).all()
    angle_err = torch.atan2(seen[0, :, 1], seen[0, :, 0]) - torch.atan2(points[0, :, 1], points[0, :, 0])
    assert (angle_err.abs() <= math.radians(0.51)).all()
    assert not torch.allclose(seen, points)
