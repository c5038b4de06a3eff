"""Skills on constructed scenes: pass speeds, GetOpen, HoldBall, interception."""

from __future__ import annotations

import math

import pytest
import torch

from hfrl_torch.envs.keepaway.params import physics_preset
from hfrl_torch.envs.keepaway.physics import KICK_KIND, TURN_KIND, kick_power_rate
from hfrl_torch.envs.keepaway.skills import (
    freeze_ball,
    get_open_grid,
    get_open_target,
    hold_ball,
    in_pass_cone,
    intercept_estimate,
    kick_ball_close_to_body,
    pass_ball,
    pass_speed,
)

P = physics_preset("2005")
T = torch.tensor


def test_pass_speeds_at_5_10_20_metres() -> None:
    speeds = pass_speed(T([5.0, 10.0, 20.0])).tolist()
    assert speeds == pytest.approx([1.54, 1.85, 2.52], abs=0.005)


def test_pass_arrives_near_end_speed() -> None:
    speed = pass_speed(T([10.0])).item()
    travelled, v = 0.0, speed
    while travelled + v < 10.0:
        travelled += v
        v *= 0.94
    assert 1.2 <= v <= 1.2 / 0.94 + 1e-6


def test_get_open_grid_for_20m() -> None:
    grid = get_open_grid(20.0, 20.0, torch.device("cpu"), torch.float32)
    assert sorted(set(grid[:, 0].tolist())) == pytest.approx([-7.0, -3.5, 0.0, 3.5, 7.0])
    assert grid.shape == (25, 2)


def test_pass_cone() -> None:
    origin, end = T([[0.0, 0.0]]), T([[10.0, 0.0]])
    others = T([[[5.0, 1.0], [5.0, 2.0], [-1.0, 0.0], [11.0, 0.0]]])
    assert in_pass_cone(origin, end, others).tolist() == [[True, False, False, False]]


def test_get_open_picks_least_congested_open_point() -> None:
    grid = get_open_grid(20.0, 20.0, torch.device("cpu"), torch.float32)
    keepers = T([[[-7.0, -7.0], [0.0, 0.0], [7.0, 7.0]]])
    takers = T([[[-6.0, -6.0], [-5.0, -7.0]]])
    pass_from = T([[-7.0, -7.0]])
    target = get_open_target(keepers, takers, pass_from, grid)
    congestion = []
    for point in grid:
        others = torch.cat((keepers[0, :2], takers[0]))
        blocked = in_pass_cone(pass_from, point[None], takers).any().item()
        congestion.append(math.inf if blocked else (1.0 / (others - point).norm(dim=-1)).sum().item())
    best = grid[int(torch.tensor(congestion).argmin())]
    assert target[0, 2].tolist() == pytest.approx(best.tolist())
    assert target[0, 2].tolist() == pytest.approx([-7.0, 7.0])  # (7, 7) is behind taker (-6, -6)


def test_get_open_falls_back_to_centre_when_every_cone_is_blocked() -> None:
    grid = get_open_grid(20.0, 20.0, torch.device("cpu"), torch.float32)
    keepers = T([[[0.0, 0.0], [5.0, 5.0], [-5.0, 5.0]]])
    ring = [[0.5 * math.cos(a), 0.5 * math.sin(a)] for a in torch.linspace(0, 2 * math.pi, 40)[:-1].tolist()]
    takers = T([ring])
    target = get_open_target(keepers, takers, T([[0.0, 0.0]]), grid)
    assert target.abs().max().item() == 0.0


def test_hold_ball_kicks_to_the_side_away_from_the_taker() -> None:
    me, vel, body = T([[0.0, 0.0]]), T([[0.0, 0.0]]), T([0.0])
    ball, ball_vel = T([[0.7, -0.1]]), T([[0.0, 0.0]])
    taker = T([[[-3.0, 0.0], [9.0, 9.0]]])
    cmd = hold_ball(me, vel, body, ball, ball_vel, taker, 0.7, 52.5, P)
    assert cmd[0, 0].item() == KICK_KIND
    rate = kick_power_rate(me, body, ball, P)
    accel = cmd[0, 1] * rate * torch.stack((torch.cos(cmd[0, 2]), torch.sin(cmd[0, 2])))
    landed = ball[0] + accel[:, 0] if accel.dim() > 1 else ball[0] + accel
    # 45 degrees off the line taker -> me, on the side where the ball already is
    assert landed.tolist() == pytest.approx([0.875 / math.sqrt(2), -0.875 / math.sqrt(2)], abs=1e-4)


def test_hold_ball_turns_when_ball_already_on_spot() -> None:
    spot = 0.875 / math.sqrt(2)
    cmd = hold_ball(
        T([[0.0, 0.0]]),
        T([[0.0, 0.0]]),
        T([0.0]),
        T([[spot, spot]]),
        T([[0.0, 0.0]]),
        T([[[-3.0, 0.0]]]),
        0.7,
        52.5,
        P,
    )
    assert cmd[0, 0].item() == TURN_KIND


def _ball_velocity_after(cmd: torch.Tensor, me, body, ball, ball_vel) -> torch.Tensor:
    rate = kick_power_rate(me, body, ball, P)
    return ball_vel + (cmd[:, 1] * rate).unsqueeze(-1) * torch.stack(
        (torch.cos(body + cmd[:, 2]), torch.sin(body + cmd[:, 2])), dim=-1
    )


def test_hold_ball_goes_in_front_of_the_body_without_a_taker_within_5m() -> None:
    me, vel, body = T([[0.0, 0.0]]), T([[0.0, 0.0]]), T([math.pi / 2])
    ball, ball_vel = T([[0.5, 0.2]]), T([[0.0, 0.0]])
    cmd = hold_ball(me, vel, body, ball, ball_vel, T([[[-5.1, 0.0], [6.0, 6.0]]]), 0.7, 52.5, P)
    landed = ball + _ball_velocity_after(cmd, me, body, ball, ball_vel)
    assert cmd[0, 0].item() == KICK_KIND
    assert landed[0].tolist() == pytest.approx([0.0, 0.875], abs=1e-4)


def test_hold_ball_side_follows_the_ball_not_the_taker_heading() -> None:
    me, vel, body = T([[0.0, 0.0], [0.0, 0.0]]), T([[0.0, 0.0], [0.0, 0.0]]), T([0.0, 0.0])
    spot = 0.875 / math.sqrt(2)
    ball = T([[spot - 0.5, spot], [spot - 0.5, -spot]])  # left / right of the line taker -> me
    ball_vel = T([[0.0, 0.0], [0.0, 0.0]])
    taker = T([[[-3.0, 0.0]], [[-3.0, 0.0]]])
    landed = ball + _ball_velocity_after(
        hold_ball(me, vel, body, ball, ball_vel, taker, 0.7, 52.5, P), me, body, ball, ball_vel
    )
    assert landed.reshape(-1).tolist() == pytest.approx([spot, spot, spot, -spot], abs=1e-4)


def test_kick_close_to_body_freezes_a_ball_it_cannot_redirect() -> None:
    """Swinging a ball that arrives at one 45-degree spot over to the other needs more than the
    maximum power: the reference's kickBallCloseToBody freezes the ball instead. The spot
    (0.875 m) lies just beyond 0.8 x 1.085 m, so freezeBall pulls it in to 0.7 x 1.085 m."""
    me, vel, body = T([[0.0, 0.0]]), T([[0.0, 0.0]]), T([0.0])
    spot = 0.875 / math.sqrt(2)
    ball, ball_vel = T([[spot, spot]]), T([[0.0, 1.16]])
    cmd = kick_ball_close_to_body(me, vel, body, ball, ball_vel, T([-math.pi / 4]), 0.7, P)
    after = ball + _ball_velocity_after(cmd, me, body, ball, ball_vel)
    inside = 0.7 * P.kickable_distance / math.sqrt(2)
    assert cmd[0, 0].item() == KICK_KIND and cmd[0, 1].item() <= 100.0
    assert after[0].tolist() == pytest.approx([inside, inside], abs=1e-4)
    # nearer the body the ball is simply stopped
    near, fast = T([[0.45, 0.45]]), T([[0.0, 1.6]])
    cmd = kick_ball_close_to_body(me, vel, body, near, fast, T([-math.pi / 4]), 0.7, P)
    assert _ball_velocity_after(cmd, me, body, near, fast)[0].tolist() == pytest.approx([0.0, 0.0], abs=1e-5)
    # a slow ball is kicked at full power towards the spot instead
    slow = kick_ball_close_to_body(me, vel, body, T([[-1.0, 0.0]]), T([[0.0, 0.05]]), T([0.0]), 0.7, P)
    assert slow[0, 1].item() == pytest.approx(100.0)


def test_freeze_pulls_in_a_ball_that_would_stop_outside_the_safe_range() -> None:
    me, vel, body = T([[0.0, 0.0]]), T([[0.0, 0.0]]), T([0.0])
    ball, ball_vel = T([[1.0, 0.0]]), T([[0.3, 0.0]])
    cmd = freeze_ball(me, vel, body, ball, ball_vel, P)
    after = ball + _ball_velocity_after(cmd, me, body, ball, ball_vel)
    assert after[0].tolist() == pytest.approx([0.7 * P.kickable_distance, 0.0], abs=1e-4)
    # a ball that stays well inside is simply stopped
    inner = freeze_ball(me, vel, body, T([[0.6, 0.0]]), T([[0.3, 0.0]]), P)
    stopped = _ball_velocity_after(inner, me, body, T([[0.6, 0.0]]), T([[0.3, 0.0]]))
    assert stopped[0].tolist() == pytest.approx([0.0, 0.0], abs=1e-5)


def test_pass_kick_gives_the_wanted_velocity() -> None:
    me, vel, body = T([[0.0, 0.0]]), T([[0.0, 0.0]]), T([0.0])
    ball = T([[0.5, 0.0]])
    cmd = pass_ball(me, vel, body, ball, T([[0.0, 0.0]]), T([[10.5, 0.0]]), T([False]), P)
    rate = 0.027 * (1 - 0.25 * (0.5 - 0.385) / 0.7)
    assert cmd[0, 0].item() == KICK_KIND
    assert (cmd[0, 1] * rate).item() == pytest.approx(pass_speed(T([10.0])).item(), abs=1e-4)
    assert cmd[0, 2].item() == pytest.approx(0.0, abs=1e-6)


def test_pass_needing_too_much_power_repositions_the_ball() -> None:
    me, vel, body = T([[0.0, 0.0]]), T([[0.0, 0.0]]), T([0.0])
    ball = T([[-1.0, 0.0]])  # behind, at the edge: kicks are half as effective
    cmd = pass_ball(me, vel, body, ball, T([[0.0, 0.0]]), T([[-21.0, 0.0]]), T([False]), P)
    rate = 0.027 * (1 - 0.25 - 0.25 * (1.0 - 0.385) / 0.7)
    accel_dir = cmd[0, 2].item()
    assert cmd[0, 1].item() * rate < pass_speed(T([20.0])).item()
    assert math.cos(accel_dir) > 0  # towards the front of the body, not towards the target


def test_stopped_ball_is_approached_directly() -> None:
    pos, vel, body = T([[[0.0, 0.0]]]), T([[[0.0, 0.0]]]), T([[0.0]])
    cycles, point = intercept_estimate(pos, vel, body, T([[5.0, 0.0]]), T([[0.0, 0.0]]), 30, P)
    assert point[0, 0].tolist() == pytest.approx([5.0, 0.0])
    # 3.915 m to cover: 0.6 + 0.84 + 0.936 + 0.974 (= 3.35) is short, a fifth dash gets there
    assert cycles[0, 0].item() == 5


def test_moving_ball_is_intercepted_on_its_path() -> None:
    pos, vel, body = T([[[5.0, 3.0]]]), T([[[0.0, 0.0]]]), T([[-math.pi / 2]])
    cycles, point = intercept_estimate(pos, vel, body, T([[0.0, 0.0]]), T([[1.5, 0.0]]), 30, P)
    assert point[0, 0, 1].item() == pytest.approx(0.0)
    assert 2.0 < point[0, 0, 0].item() < 9.0
    assert 1 <= cycles[0, 0].item() <= 30


def _played_state(batch: int, preset: str) -> tuple:
    from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawaySimulator, hand_coded_actions

    sim = KeepawaySimulator(batch, KeepawayConfig(preset=preset, **TASKS["exact"]), seed=3)
    for _ in range(25):
        obs, _ = sim.observe(sim.decision().holder)
        sim.step(hand_coded_actions(obs, 3, 2), auto_reset=True)
    return sim.state, sim.physics, sim.grid


@pytest.mark.parametrize("preset", ["2005", "rcss19"])
def test_blocked_look_ahead_matches_one_block(preset: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The CPU block size of GoToBall's look-ahead and GetOpen's grid changes no bit."""
    import hfrl_torch.envs.keepaway.skills as skills

    state, physics, grid = _played_state(700, preset)
    args = (
        state.pos[:, 1:],
        state.vel[:, 1:],
        state.body[:, 1:],
        state.ball_pos,
        state.ball_vel,
        30,
        physics,
    )
    pass_from = state.ball_pos + state.ball_vel
    monkeypatch.setattr(skills, "INTERCEPT_BLOCK", 10_000)
    cycles, points = intercept_estimate(*args)
    target = get_open_target(state.keeper_pos, state.taker_pos, pass_from, grid)
    monkeypatch.setattr(skills, "INTERCEPT_BLOCK", 64)
    cycles_b, points_b = intercept_estimate(*args)
    assert torch.equal(cycles, cycles_b) and torch.equal(points, points_b)
    assert torch.equal(target, get_open_target(state.keeper_pos, state.taker_pos, pass_from, grid))
    assert (cycles >= 0).all() and bool((cycles <= 30).any())
