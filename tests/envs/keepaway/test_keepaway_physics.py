"""Physics of one cycle against hand-computed values, plus property tests."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.envs.keepaway.params import physics_preset
from hfrl_torch.envs.keepaway.physics import (
    dash_acceleration,
    kick_acceleration,
    kick_power_rate,
    move,
    resolve_collisions,
    turn_body,
)

P2005 = physics_preset("2005")
P19 = physics_preset("rcss19")
T = torch.tensor


def _move_ball(pos: torch.Tensor, vel: torch.Tensor, cycles: int) -> tuple[torch.Tensor, torch.Tensor]:
    one = torch.ones(1, dtype=torch.float64)
    for _ in range(cycles):
        pos, vel = move(
            pos,
            vel,
            torch.zeros_like(vel),
            one * 2.7,
            one * P2005.ball_speed_max,
            one * 0.94,
            one * 0.05,
            False,
        )
    return pos, vel


def test_ball_decays_geometrically() -> None:
    pos, vel = _move_ball(torch.zeros(1, 2, dtype=torch.float64), T([[2.0, 0.0]], dtype=torch.float64), 10)
    assert vel[0, 0].item() == pytest.approx(2.0 * 0.94**10)
    assert pos[0, 0].item() == pytest.approx(2.0 * (1 - 0.94**10) / 0.06)
    assert pos[0, 1].item() == 0.0


def test_kick_effectiveness_front_and_edge() -> None:
    me = T([[0.0, 0.0]])
    body = T([0.0])
    touching_front = kick_power_rate(me, body, T([[0.385, 0.0]]), P2005)
    assert touching_front.item() == pytest.approx(0.027)
    side_mid = kick_power_rate(me, body, T([[0.0, 0.385 + 0.35]]), P2005)
    assert side_mid.item() == pytest.approx(0.027 * (1 - 0.25 * 0.5 - 0.25 * 0.5))
    behind_edge = kick_power_rate(me, body, T([[-1.085, 0.0]]), P2005)
    assert behind_edge.item() == pytest.approx(0.027 * 0.5)


def test_kick_acceleration_direction_and_range() -> None:
    me, body = T([[0.0, 0.0]]), T([math.pi / 2])
    ball, still = T([[0.0, 0.385]]), T([[0.0, 0.0]])
    acc = kick_acceleration(me, body, ball, still, T([100.0]), T([-math.pi / 2]), P2005)
    assert acc[0].tolist() == pytest.approx([2.7, 0.0], abs=1e-5)
    far = kick_acceleration(me, body, T([[0.0, 1.2]]), still, T([100.0]), T([0.0]), P2005)
    assert far.abs().sum().item() == 0.0
    overpowered = kick_acceleration(me, body, ball, still, T([250.0]), T([0.0]), P2005)
    assert overpowered[0, 1].item() == pytest.approx(2.7, abs=1e-5)


def test_dash_acceleration_and_backward_dash_by_preset() -> None:
    assert dash_acceleration(T([0.0]), T([100.0]), P2005)[0].tolist() == pytest.approx([0.6, 0.0])
    assert dash_acceleration(T([0.0]), T([-100.0]), P2005)[0].tolist() == pytest.approx([-0.6, 0.0])
    assert dash_acceleration(T([0.0]), T([-100.0]), P19)[0].tolist() == pytest.approx([0.0, 0.0])


def test_player_speed_and_acceleration_caps() -> None:
    one = torch.ones(1)
    pos, vel = move(
        torch.zeros(1, 1, 2),
        T([[[0.5, 0.0]]]),
        T([[[5.0, 0.0]]]),
        one * 1.0,
        one * 1.2,
        one * 0.4,
        one * 0.1,
        False,
    )
    assert pos[0, 0, 0].item() == pytest.approx(1.2)
    assert vel[0, 0, 0].item() == pytest.approx(0.48)
    pos, _ = move(
        torch.zeros(1, 1, 2), T([[[0.0, 0.0]]]), T([[[5.0, 0.0]]]), one, one * 1.2, one * 0.4, one, False
    )
    assert pos[0, 0, 0].item() == pytest.approx(1.0)


def test_turn_is_reduced_by_inertia() -> None:
    turned = turn_body(T([0.0]), T([math.pi / 2]), T([0.2]), P2005)
    assert turned.item() == pytest.approx(math.pi / 4)
    capped = turn_body(T([0.0]), T([10.0]), T([0.0]), P2005)
    assert capped.abs().item() == pytest.approx(math.pi, abs=1e-5)


def test_collision_push_out_and_velocity_reversal() -> None:
    pos = T([[[0.0, 0.0], [0.4, 0.0], [5.0, 5.0]]])
    vel = T([[[1.0, 0.0], [-0.5, 0.0], [0.3, 0.0]]])
    radius = T([0.3, 0.3, 0.3])
    new_pos, new_vel, collided = resolve_collisions(pos, vel, radius)
    gap = (new_pos[0, 1] - new_pos[0, 0]).norm().item()
    assert gap == pytest.approx(0.6, abs=1e-3)
    assert new_pos[0, :2].mean(0).tolist() == pytest.approx([0.2, 0.0], abs=1e-6)
    assert new_vel[0, 0].tolist() == pytest.approx([-0.1, 0.0])
    assert new_vel[0, 1].tolist() == pytest.approx([0.05, 0.0])
    assert collided[0].tolist() == [True, True, False]
    assert new_pos[0, 2].tolist() == [5.0, 5.0]


def test_ball_player_collision_distance() -> None:
    pos = T([[[0.0, 0.0], [0.2, 0.0]]])
    new_pos, _, collided = resolve_collisions(pos, torch.zeros_like(pos), T([0.085, 0.3]))
    assert (new_pos[0, 1] - new_pos[0, 0]).norm().item() >= 0.385
    assert collided.all()


@settings(max_examples=60, deadline=None)
@given(
    vel=st.lists(st.floats(-3, 3), min_size=2, max_size=2),
    acc=st.lists(st.floats(-5, 5), min_size=2, max_size=2),
    noisy=st.booleans(),
    polar=st.booleans(),
)
def test_speed_never_exceeds_cap(vel: list[float], acc: list[float], noisy: bool, polar: bool) -> None:
    one = torch.ones(1, dtype=torch.float64)
    pos0 = torch.zeros(1, 1, 2, dtype=torch.float64)
    noise = (
        torch.rand(1, 1, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
        if noisy
        else None
    )
    pos, new_vel = move(
        pos0,
        T([[vel]], dtype=torch.float64),
        T([[acc]], dtype=torch.float64),
        one,
        one * 1.2,
        one * 0.4,
        one * 0.1,
        polar,
        noise,
    )
    bound = 1.2 * (1 + 0.1 * math.sqrt(2)) if noisy else 1.2
    assert pos.norm().item() <= bound + 1e-9
    assert new_vel.norm().item() <= 0.4 * bound + 1e-9


@settings(max_examples=60, deadline=None)
@given(points=st.lists(st.tuples(st.floats(-2, 2), st.floats(-2, 2)), min_size=2, max_size=4, unique=True))
def test_collision_resolution_leaves_no_overlap(points: list[tuple[float, float]]) -> None:
    pos = T([points], dtype=torch.float64)
    radius = T([0.085] + [0.3] * (len(points) - 1), dtype=torch.float64)
    # Each pass about halves what a chain of pushes leaves (four in a line need ~20 passes).
    new_pos, _, _ = resolve_collisions(pos, torch.zeros_like(pos), radius, max_passes=60)
    diff = new_pos[0, :, None] - new_pos[0, None]
    dist = diff.norm(dim=-1)
    contact = radius[:, None] + radius[None]
    off_diagonal = ~torch.eye(len(points), dtype=torch.bool)
    assert (dist[off_diagonal] >= contact[off_diagonal] - 1e-6).all()
