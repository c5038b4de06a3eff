"""What the keepers do in a cycle: the keeper with the ball executes its macro-action
(HoldBall or PassBall), the keeper predicted to reach the ball first runs GoToBall, the others
GetOpen."""

from __future__ import annotations

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.params import PhysicsParams
from hfrl_torch.envs.keepaway.physics import norm
from hfrl_torch.envs.keepaway.skills import (
    GOAL_X,
    HOLD_RATIO_KEEPER,
    choose,
    get_open,
    get_open_target,
    hold_ball,
    intercept_move,
    pass_ball,
)
from hfrl_torch.envs.keepaway.state_vars import gather_points

PASS_OPPONENT_RANGE = 2.0


def fastest_keeper(intercept_cycles: Tensor, holder: Tensor, holder_kickable: Tensor) -> Tensor:
    """The keeper [B] that reaches the ball first (the kicking holder if there is one)."""
    cycles = intercept_cycles.scatter(
        1,
        holder.unsqueeze(-1),
        torch.where(
            holder_kickable, -1, intercept_cycles.gather(1, holder.unsqueeze(-1)).squeeze(-1)
        ).unsqueeze(-1),
    )
    return cycles.argmin(-1)


def keeper_commands(
    keeper_pos: Tensor,
    keeper_vel: Tensor,
    keeper_body: Tensor,
    taker_pos: Tensor,
    taker_body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    ball_traj: Tensor,
    rest_point: Tensor,
    intercept_cycles: Tensor,
    intercept_point: Tensor,
    holder: Tensor,
    holder_kickable: Tensor,
    pass_target: Tensor,
    grid: Tensor,
    physics: PhysicsParams,
    kernels: str = "auto",
    hold_rule: str = "spec",
) -> tuple[Tensor, Tensor]:
    """Commands [B, n, 3] of all keepers, and the keeper with (or next to get) the ball [B].

    :param holder: keeper closest to the ball [B]; it acts on its macro-action when
        ``holder_kickable``.
    :param pass_target: keeper the holder passes to, -1 for HoldBall [B].
    :param grid: GetOpen candidates [25, 2].
    :param kernels: how GetOpen's search runs (``KeepawayConfig.kernels``).
    :param hold_rule: HoldBall's rule (``KeepawayConfig.hold_ball``; "reference" reads ``taker_body``).
    """
    batch, keepers = keeper_pos.shape[:2]
    horizon = ball_traj.shape[-2] - 1
    fastest = fastest_keeper(intercept_cycles, holder, holder_kickable)
    fastest_cycles = intercept_cycles.gather(1, fastest.unsqueeze(-1)).squeeze(-1).clamp_min(0)
    within = fastest_cycles <= horizon
    pass_from = torch.where(
        within.unsqueeze(-1),
        gather_points(ball_traj, fastest_cycles.clamp(max=horizon).unsqueeze(-1)).squeeze(1),
        rest_point,
    )
    ball_b = ball_pos.unsqueeze(-2).expand_as(keeper_pos)
    open_target = get_open_target(keeper_pos, taker_pos, pass_from, grid, kernels)
    cmd = get_open(keeper_pos, keeper_vel, keeper_body, open_target, ball_b, physics)
    # only the fastest keeper runs GoToBall: evaluate it for that keeper alone
    f = fastest.unsqueeze(-1)
    go = intercept_move(
        gather_points(keeper_pos, f).squeeze(1),
        gather_points(keeper_vel, f).squeeze(1),
        keeper_body.gather(1, f).squeeze(1),
        gather_points(intercept_point, f).squeeze(1),
        ball_pos,
        physics,
    )
    is_fastest = torch.arange(keepers, device=keeper_pos.device).unsqueeze(0) == f
    cmd = choose(is_fastest, go.unsqueeze(1).expand(batch, keepers, 3), cmd)

    h = holder.unsqueeze(-1)
    pos = gather_points(keeper_pos, h).squeeze(1)
    vel = gather_points(keeper_vel, h).squeeze(1)
    body = keeper_body.gather(1, h).squeeze(1)
    hold = hold_ball(
        pos,
        vel,
        body,
        ball_pos,
        ball_vel,
        taker_pos,
        HOLD_RATIO_KEEPER,
        GOAL_X,
        physics,
        taker_body,
        hold_rule,
    )
    target_pos = gather_points(keeper_pos, pass_target.clamp_min(0).unsqueeze(-1)).squeeze(1)
    opponent_near = (norm(taker_pos - ball_pos.unsqueeze(-2)) < PASS_OPPONENT_RANGE).any(-1)
    kick = pass_ball(pos, vel, body, ball_pos, ball_vel, target_pos, opponent_near, physics)
    macro = choose(pass_target >= 0, kick, hold)
    is_holder = (
        torch.arange(keepers, device=keeper_pos.device).unsqueeze(0) == h
    ) & holder_kickable.unsqueeze(-1)
    cmd = choose(is_holder, macro.unsqueeze(1).expand(batch, keepers, 3), cmd)
    return cmd, fastest
