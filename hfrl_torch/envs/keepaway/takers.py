"""The takers' fixed policy (Hand-coded-T; with two takers it is All-to-ball)."""

from __future__ import annotations

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.params import PhysicsParams
from hfrl_torch.envs.keepaway.physics import norm
from hfrl_torch.envs.keepaway.skills import (
    GOAL_X,
    HOLD_RATIO_TAKER,
    block_pass,
    block_pass_target,
    choose,
    face_point,
    hold_ball,
    intercept_move,
)


def taker_commands(
    keeper_pos: Tensor,
    keeper_body: Tensor,
    taker_pos: Tensor,
    taker_vel: Tensor,
    taker_body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    intercept_point: Tensor,
    keeper_with_ball: Tensor,
    physics: PhysicsParams,
    hold_rule: str = "spec",
) -> Tensor:
    """Commands [B, m, 3] of all takers for this cycle.

    The taker closest to the ball holds it when it can kick it; the two takers closest to the
    ball go to it (a taker whose teammate is the player closest to the ball and can kick it
    just faces the ball); any further taker blocks the pass to the most open keeper.

    :param intercept_point: GoToBall points of the takers [B, m, 2].
    :param keeper_with_ball: the keeper that has or will first get the ball [B].
    :param hold_rule: HoldBall's rule (``KeepawayConfig.hold_ball``; "reference" reads ``keeper_body``).
    """
    batch, takers = taker_pos.shape[:2]
    kickable = physics.kickable_distance
    taker_dist = norm(taker_pos - ball_pos.unsqueeze(-2))
    rank = torch.argsort(torch.argsort(taker_dist, dim=-1, stable=True), dim=-1, stable=True)
    go = intercept_move(
        taker_pos,
        taker_vel,
        taker_body,
        intercept_point,
        ball_pos.unsqueeze(-2).expand_as(taker_pos),
        physics,
    )
    keeper_dist = norm(keeper_pos - ball_pos.unsqueeze(-2))
    nearest_taker = taker_dist.min(-1)
    taker_closest_overall = nearest_taker.values < keeper_dist.min(-1).values
    mate_has_it = (
        taker_closest_overall.unsqueeze(-1) & (nearest_taker.values <= kickable).unsqueeze(-1) & (rank != 0)
    )
    face = face_point(taker_pos, taker_vel, taker_body, ball_pos.unsqueeze(-2).expand_as(taker_pos), physics)
    cmd = choose(mate_has_it, face, go)
    if takers > 2:
        target = block_pass_target(keeper_pos, taker_pos, keeper_with_ball, ball_pos)
        block = block_pass(
            taker_pos,
            taker_vel,
            taker_body,
            target.unsqueeze(-2).expand_as(taker_pos),
            ball_pos.unsqueeze(-2).expand_as(taker_pos),
            physics,
        )
        cmd = choose(rank >= 2, block, cmd)
    first = nearest_taker.indices
    idx = first[:, None, None]
    hold = hold_ball(
        torch.gather(taker_pos, 1, idx.expand(-1, 1, 2)).squeeze(1),
        torch.gather(taker_vel, 1, idx.expand(-1, 1, 2)).squeeze(1),
        torch.gather(taker_body, 1, first[:, None]).squeeze(1),
        ball_pos,
        ball_vel,
        keeper_pos,
        HOLD_RATIO_TAKER,
        -GOAL_X,
        physics,
        keeper_body,
        hold_rule,
    )
    holding = (nearest_taker.values <= kickable).unsqueeze(-1) & (rank == 0)
    return choose(holding, hold.unsqueeze(1).expand(batch, takers, 3), cmd)
