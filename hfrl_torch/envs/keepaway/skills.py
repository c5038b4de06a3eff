"""Player skills of the UT Austin keepaway players, batched: turn/dash primitives, HoldBall,
PassBall, GoToBall (interception with look-ahead), GetOpen and BlockPass.

A command is a tensor [..., 3] = (kind, power, angle): kind 0 none, 1 turn (angle = moment),
2 dash (power), 3 kick (power, angle = direction relative to the body).
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.params import PhysicsParams, resolve_kernels
from hfrl_torch.envs.keepaway.physics import (
    DASH_KIND,
    KICK_KIND,
    TURN_KIND,
    direction,
    dot,
    hypot_f64,
    kick_power_rate,
    norm,
    unit,
    wrap_angle,
)

WHEN_TO_TURN = math.radians(7.0)  # PlayerWhenToTurnAngle
MARK_TURN = math.radians(25.0)  # turn threshold of mark()
GET_OPEN_BUFFER = 1.5  # within this distance of the GetOpen point, face the ball
MARK_DISTANCE = 4.0  # BlockPass stands this far from the marked keeper, towards the ball
MARK_BUFFER = 2.0
HOLD_RATIO_KEEPER = 0.7  # HoldBall puts the ball at player+ball size + ratio * kickable_margin
HOLD_RATIO_TAKER = 0.3
REPOSITION_RATIO = 0.16  # kickBallCloseToBody's default ratio
HOLD_OPPONENT_RANGE = 5.0  # HoldBall heeds the nearest opponent within this distance
HOLD_SIDE_ANGLE = math.radians(45.0)  # ... and puts the ball this far off the line from it
HOLD_SPOT_TOLERANCE = 0.3  # HoldBall turns instead of kicking when the ball lies this close to its spot
HOLD_STAYS = 0.85  # ... and stays within this share of the kickable distance next cycle
PASS_END_SPEED = 1.2
WHEN_TO_KICK = 0.85  # PlayerWhenToKick
PASS_POWER_RATIO = 1.05  # PassBall kicks if it needs at most this share of the maximum power ...
PASS_POWER_RATIO_PRESSED = 1.30  # ... or this share with an opponent near the ball
FREEZE_MIN_SPEED = 0.1  # kickBallCloseToBody freezes a ball faster than this that it cannot redirect
FREEZE_STAYS = 0.8  # freezeBall stops the ball if it then lies within this share of the kickable distance
FREEZE_PULL_REACH = 0.7  # ... else pulls it to this share of the kickable distance from the player
FREEZE_PULL_GAP = 0.1  # ... or its distance less this, if nearer
INTERCEPT_FACE_DISTANCE = 0.5  # GoToBall faces the ball with its rolled-out position this near the point
INTERCEPT_BEHIND_DISTANCE = 2.5  # ... turns to a point behind it farther than this
INTERCEPT_FAR, INTERCEPT_MID = 20.0, 10.0  # ... and to one off its body line (distances to the point)
INTERCEPT_LATERAL_FAR, INTERCEPT_LATERAL_MID, INTERCEPT_LATERAL_NEAR = 3.0, 2.0, 0.9  # x kickable distance
GOAL_X = 52.5  # the pitch's goal line, the point HoldBall turns to when the ball lies well
CONE_WIDTH = 0.3  # GetOpen's pass cone: off-line distance per metre along the pass
BLOCKED_PENALTY = 1e9  # congestion added to a GetOpen point whose pass cone holds a taker


def command(kind: int | Tensor, power: Tensor | float, angle: Tensor | float, like: Tensor) -> Tensor:
    """A command tensor [..., 3] shaped like ``like`` [...]."""
    kind_t = torch.as_tensor(kind, dtype=like.dtype, device=like.device).expand_as(like)
    power_t = torch.as_tensor(power, dtype=like.dtype, device=like.device).expand_as(like)
    angle_t = torch.as_tensor(angle, dtype=like.dtype, device=like.device).expand_as(like)
    return torch.stack((kind_t, power_t, angle_t), dim=-1)


def choose(mask: Tensor, if_true: Tensor, if_false: Tensor) -> Tensor:
    """Per-player choice between two commands."""
    return torch.where(mask.unsqueeze(-1), if_true, if_false)


def pass_speed(distance: Tensor, end_speed: float = PASS_END_SPEED, decay: float = 0.94) -> Tensor:
    """First speed of a pass that arrives with ``end_speed`` after ``distance`` metres.

    v0 = end * (1/decay)^n with n the smallest whole number of cycles whose backward series
    sum_{i<n} end (1/decay)^i covers the distance (1.54, 1.85, 2.52 m/cycle at 5, 10, 20 m).
    """
    ratio = 1.0 / decay
    cycles = torch.log1p(distance.clamp_min(0.0) * (ratio - 1.0) / end_speed) / math.log(ratio)
    cycles = torch.ceil(cycles - 1e-6).clamp_min(0.0)
    return end_speed * torch.pow(torch.full_like(cycles, ratio), cycles)


# ----------------------------------------------------------------- turn and dash primitives


def turn_moment_to_point(
    pos: Tensor, vel: Tensor, body: Tensor, target: Tensor, physics: PhysicsParams
) -> Tensor:
    """Turn moment that points the body at ``target`` from next cycle's position, compensating
    the inertia of a moving player (the server caps it at 180 degrees)."""
    err = wrap_angle(direction(target - (pos + vel)) - body)
    moment = err * (1.0 + physics.inertia_moment * norm(vel))
    return moment.clamp(-physics.max_moment, physics.max_moment)


def face_point(pos: Tensor, vel: Tensor, body: Tensor, target: Tensor, physics: PhysicsParams) -> Tensor:
    """Turn command towards ``target``."""
    return command(TURN_KIND, 0.0, turn_moment_to_point(pos, vel, body, target, physics), body)


def dash_power_to_point(
    pos: Tensor, vel: Tensor, body: Tensor, target: Tensor, physics: PhysicsParams
) -> Tensor:
    """Dash power that brings the player as close to ``target`` as one dash can (players'
    getPowerForDash): full power unless the target is less than a step ahead."""
    heading = unit(body)
    wanted = dot(target - pos, heading).clamp(max=physics.player_speed_max)
    accel = wanted - dot(vel, heading)
    return (accel / physics.dash_power_rate).clamp(physics.min_dash_power, physics.max_power)


def rolled_out(pos: Tensor, vel: Tensor, physics: PhysicsParams) -> Tensor:
    """Where a player stops if it issues no more commands."""
    return pos + vel / (1.0 - physics.player_decay)


def move_to_point(
    pos: Tensor, vel: Tensor, body: Tensor, target: Tensor, turn_threshold: float, physics: PhysicsParams
) -> Tensor:
    """Turn if the heading error (seen from the rolled-out position) exceeds ``turn_threshold``,
    else dash towards ``target`` (moveToPos)."""
    err = wrap_angle(direction(target - rolled_out(pos, vel, physics)) - body)
    turn = face_point(pos, vel, body, target, physics)
    dash = command(DASH_KIND, dash_power_to_point(pos, vel, body, target, physics), 0.0, body)
    return choose(err.abs() > turn_threshold, turn, dash)


def intercept_move(
    pos: Tensor, vel: Tensor, body: Tensor, target: Tensor, ball_pos: Tensor, physics: PhysicsParams
) -> Tensor:
    """Command towards an interception point (predictCommandToMoveToPos).

    Turns only when the point lies off the body line by more than a distance-dependent
    multiple of the kickable distance, or behind and more than 2.5 m away, and the heading
    error exceeds 7 degrees; otherwise dashes (backwards when the preset allows). A player whose
    rolled-out position is within 0.5 m of the point turns to face the ball instead.
    """
    kickable = physics.kickable_distance
    pred = rolled_out(pos, vel, physics)
    rel = target - pred
    heading = unit(body)
    lateral = (heading[..., 0] * rel[..., 1] - heading[..., 1] * rel[..., 0]).abs()
    far = norm(target - pos)
    ratio = torch.where(
        far > INTERCEPT_FAR,
        INTERCEPT_LATERAL_FAR,
        torch.where(far > INTERCEPT_MID, INTERCEPT_LATERAL_MID, INTERCEPT_LATERAL_NEAR),
    )
    err = wrap_angle(direction(rel) - body)
    behind = (norm(rel) > INTERCEPT_BEHIND_DISTANCE) & (err.abs() > 0.5 * math.pi)
    turn_needed = ((lateral > ratio * kickable) | behind) & (err.abs() > WHEN_TO_TURN)
    turn = face_point(pos, vel, body, target, physics)
    dash = command(DASH_KIND, dash_power_to_point(pos, vel, body, target, physics), 0.0, body)
    move = choose(turn_needed, turn, dash)
    return choose(norm(rel) < INTERCEPT_FACE_DISTANCE, face_point(pos, vel, body, ball_pos, physics), move)


# ----------------------------------------------------------------------------- GoToBall


def predict_ball(ball_pos: Tensor, ball_vel: Tensor, decay: float, horizon: int) -> Tensor:
    """Ball positions [B, horizon + 1, 2] after 0..horizon cycles without kicks or noise."""
    steps = torch.arange(horizon + 1, device=ball_pos.device, dtype=ball_pos.dtype)
    travelled = (1.0 - torch.pow(torch.full_like(steps, decay), steps)) / (1.0 - decay)
    return ball_pos.unsqueeze(-2) + travelled.unsqueeze(-1) * ball_vel.unsqueeze(-2)


def ball_rest_point(ball_pos: Tensor, ball_vel: Tensor, decay: float) -> Tensor:
    """Where the ball stops if nobody touches it."""
    return ball_pos + ball_vel / (1.0 - decay)


@functools.lru_cache(maxsize=16)
def _reach_table(horizon: int, physics: PhysicsParams, device: torch.device, dtype: torch.dtype) -> Tensor:
    """Distance [4, H + 1] a resting player covers by cycle i after t = 0..3 turns (dashing
    at full power the remaining i - t cycles); -1 where no dash fits."""
    decay = physics.player_decay
    accel = min(physics.max_power * physics.dash_power_rate, physics.player_accel_max)
    cruise = min(accel / (1.0 - decay), physics.player_speed_max)
    first = min(accel, physics.player_speed_max)
    table = torch.full((4, horizon + 1), -1.0, dtype=torch.float64)
    for turns in range(4):
        for cycle in range(turns + 1, horizon + 1):
            dashes = cycle - turns
            table[turns, cycle] = dashes * cruise + (first - cruise) * (1.0 - decay**dashes) / (1.0 - decay)
    return table.to(device=device, dtype=dtype)


_WORKSPACE: dict[tuple, Tensor] = {}


def _scratch(slot: str, shape: tuple[int, ...], like: Tensor, dtype: torch.dtype | None = None) -> Tensor:
    """A reusable scratch tensor (CPU allocation and first touch of large temporaries cost more
    than the arithmetic); only for values that do not leave the function using it."""
    key = (slot, shape, like.device, dtype or like.dtype)
    buf = _WORKSPACE.get(key)
    if buf is None:
        if len(_WORKSPACE) > 64:
            _WORKSPACE.clear()
        buf = _WORKSPACE[key] = torch.empty(shape, device=like.device, dtype=dtype or like.dtype)
    return buf


# Fields per block of the look-ahead on CPU: [H + 1, block, P] temporaries stay in the cache.
INTERCEPT_BLOCK = 1024


def intercept_estimate(
    pos: Tensor,
    vel: Tensor,
    body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    horizon: int,
    physics: PhysicsParams,
    kernels: str = "auto",
) -> tuple[Tensor, Tensor]:
    """Cycles until each player can have the ball within kickable distance, and where.

    For every look-ahead cycle i the player needs the turns to face the ball's position
    (each turn limited by its inertia, the speed decaying between turns) and then full-power
    dashes covering the distance less the kickable distance; the first i where that fits is the
    interception. If no cycle of the horizon fits, the player runs to the ball's rest point.
    The ball moves on a straight line, so everything reduces to scalars per (cycle, player),
    laid out [H + 1, B, P] so that the reductions over cycles are elementwise (on CPU in blocks
    of fields that stay in the cache), or searched cycle by cycle by a numba kernel.

    :param pos: player positions [B, P, 2]; ``vel`` alike, ``body`` [B, P].
    :param ball_pos: ball position [B, 2]; ``ball_vel`` alike.
    :param kernels: ``"numba"``, ``"torch"`` or ``"auto"`` (see :func:`resolve_kernels`).
    :returns: cycles [B, P] (long) and interception points [B, P, 2].
    """
    decay = physics.player_decay
    accel = min(physics.max_power * physics.dash_power_rate, physics.player_accel_max)
    cruise = min(accel / (1.0 - decay), physics.player_speed_max)
    cycles_1d = torch.arange(horizon + 1, device=pos.device, dtype=pos.dtype)
    travel = (1.0 - torch.pow(torch.full_like(cycles_1d, physics.ball_decay), cycles_1d)) / (
        1.0 - physics.ball_decay
    )
    series = (1.0 - torch.pow(torch.full_like(cycles_1d, decay), cycles_1d)) / (1.0 - decay)
    cruise_part = cycles_1d * cruise
    table = _reach_table(horizon, physics, pos.device, pos.dtype)  # [4, H+1]
    body = body.contiguous()
    hx, hy = torch.cos(body), torch.sin(body)
    # t turns fit when the heading error is within the first t turns' reach (+7 degrees); the
    # turn counts are nested and fewer turns leave more dashing, so the reachable distance is
    # that of the fewest turns whose limit covers the heading error
    speed = norm(vel)
    cos_limits = []
    capacity = torch.zeros_like(speed)
    for t in range(3):
        cos_limits.append(torch.cos((capacity + WHEN_TO_TURN).clamp(max=math.pi)))
        capacity = capacity + (math.pi / (1.0 + physics.inertia_moment * speed * decay**t)).clamp(max=math.pi)
    if resolve_kernels(kernels, pos.device, pos.dtype) == "numba":
        from hfrl_torch.envs.keepaway.kernels_numba import intercept_search

        cycles = torch.empty(pos.shape[:2], dtype=torch.long)
        points = torch.empty_like(pos)
        consts = [physics.kickable_distance, 1e-12, 0.0, 1.0, 2.0, accel, physics.player_speed_max, cruise]
        intercept_search(
            *(t.contiguous().numpy() for t in (pos, vel, hx, hy, ball_pos, ball_vel)),
            torch.stack(cos_limits).numpy(),
            *(t.numpy() for t in (travel, travel * travel, series, cruise_part, table)),
            torch.tensor([*consts, 1.0 - physics.ball_decay], dtype=torch.float32).numpy(),
            cycles.numpy(),
            points.numpy(),
        )
        return cycles, points
    return _intercept_torch(
        pos,
        vel,
        hx,
        hy,
        ball_pos,
        ball_vel,
        cos_limits,
        travel,
        series,
        cruise_part,
        table,
        accel,
        cruise,
        physics,
    )


def _intercept_torch(
    pos: Tensor,
    vel: Tensor,
    hx: Tensor,
    hy: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    cos_limits: list[Tensor],
    travel_1d: Tensor,
    series_1d: Tensor,
    cruise_1d: Tensor,
    table_2d: Tensor,
    accel: float,
    cruise: float,
    physics: PhysicsParams,
) -> tuple[Tensor, Tensor]:
    """:func:`intercept_estimate` with tensor ops, the twin of ``kernels_numba.intercept_search``:
    per (field, player) coefficients of the quadratics in the ball's travel, then all cycles at
    once, the first reachable one marked by the largest weight H + 1 - i."""
    horizon = travel_1d.shape[0] - 1
    travel = travel_1d[:, None, None]
    travel_sq = travel * travel
    series, cruise_part = series_1d[:, None, None], cruise_1d[:, None, None]
    table = table_2d[:, :, None, None]
    vx, vy = ball_vel[:, None, 0], ball_vel[:, None, 1]
    v_sq = vx * vx + vy * vy
    dx = ball_pos[:, None, 0] - pos[..., 0]
    dy = ball_pos[:, None, 1] - pos[..., 1]
    ex, ey = dx - vel[..., 0], dy - vel[..., 1]
    need_lin = 2.0 * (dx * vx + dy * vy)
    need_const = dx * dx + dy * dy
    err_lin = 2.0 * (ex * vx + ey * vy)
    err_const = ex * ex + ey * ey + 1e-12
    head_lin = vx * hx + vy * hy
    head_const = ex * hx + ey * hy
    forward = (vel[..., 0] * hx + vel[..., 1] * hy).clamp_min(0.0)
    first_gap = (forward + accel).clamp(max=physics.player_speed_max) - cruise
    weights = _weights(horizon, pos.device)
    batch, players = pos.shape[:2]
    block = batch if pos.device.type != "cpu" else INTERCEPT_BLOCK
    score = torch.empty(batch, players, dtype=torch.uint8, device=pos.device)
    for lo in range(0, batch, block):
        hi = min(lo + block, batch)
        shape = (horizon + 1, hi - lo, players)
        need = _scratch("need", shape, pos)
        err = _scratch("err", shape, pos)
        tmp = _scratch("tmp", shape, pos)
        reach = _scratch("reach", shape, pos)
        ready = _scratch("ready", shape, pos, torch.bool)
        can = _scratch("can", shape, pos, torch.uint8)
        moved = _scratch("moved", (horizon + 1, hi - lo, 1), pos)
        torch.mul(travel_sq, v_sq[lo:hi], out=moved)  # not addcmul: no fused multiply-add
        torch.mul(travel, need_lin[lo:hi], out=need)
        need.add_(need_const[lo:hi]).add_(moved).clamp_min_(0.0).sqrt_().sub_(physics.kickable_distance)
        torch.mul(travel, err_lin[lo:hi], out=err)
        err.add_(err_const[lo:hi]).add_(moved).clamp_min_(1e-12).rsqrt_()
        torch.mul(travel, head_lin[lo:hi], out=tmp)
        err.mul_(tmp.add_(head_const[lo:hi]))
        torch.mul(series, first_gap[lo:hi], out=reach)
        reach.add_(cruise_part)
        # reachable distance: table[3] by default, fewer turns where the heading error allows
        torch.ge(err, cos_limits[2][lo:hi], out=ready)
        torch.where(ready, table[2], table[3], out=tmp)
        torch.ge(err, cos_limits[1][lo:hi], out=ready)
        torch.where(ready, table[1], tmp, out=tmp)
        torch.ge(err, cos_limits[0][lo:hi], out=ready)
        torch.where(ready, reach, tmp, out=tmp)
        torch.le(need, tmp, out=ready)
        torch.mul(ready, weights, out=can)
        torch.amax(can, 0, out=score[lo:hi])
    found = score > 0
    first_cycle = (horizon + 1 - score.long()).clamp(max=horizon)
    along = travel_1d[first_cycle]
    point = ball_pos.unsqueeze(1) + along.unsqueeze(-1) * ball_vel.unsqueeze(1)
    rest = (ball_pos + ball_vel / (1.0 - physics.ball_decay)).unsqueeze(1).expand_as(point)
    to_rest = rest - pos
    fallback_cycles = horizon + 1 + torch.ceil(hypot_f64(to_rest[..., 0], to_rest[..., 1]) / cruise).long()
    cycles = torch.where(found, first_cycle, fallback_cycles)
    return cycles, torch.where(found.unsqueeze(-1), point, rest)


@functools.lru_cache(maxsize=16)
def _weights(horizon: int, device: torch.device) -> Tensor:
    """H + 1 - i for cycle i [H + 1, 1, 1]: the largest weight of a reachable cycle marks the first."""
    return torch.arange(horizon + 1, 0, -1, device=device, dtype=torch.uint8)[:, None, None]


# ------------------------------------------------------------------------------- kicking


def kick_for_acceleration(accel: Tensor, rate: Tensor, body: Tensor) -> Tensor:
    """Kick command that gives the ball acceleration ``accel`` (power not yet capped)."""
    return command(KICK_KIND, norm(accel) / rate.clamp_min(1e-6), wrap_angle(direction(accel) - body), body)


def accelerate_ball_to_velocity(
    vel_des: Tensor, ball_vel: Tensor, rate: Tensor, body: Tensor, physics: PhysicsParams
) -> Tensor:
    """Kick giving the ball velocity ``vel_des``; if out of reach, a full-power kick that at
    least makes the ball move along ``vel_des`` (accelerateBallToVelocity)."""
    acc_des = vel_des - ball_vel
    exact = kick_for_acceleration(acc_des, rate, body)
    reachable = (norm(acc_des) < physics.ball_accel_max) & (exact[..., 1] <= physics.max_power)
    heading = direction(vel_des)
    across = -torch.sin(heading) * ball_vel[..., 0] + torch.cos(heading) * ball_vel[..., 1]
    full_speed = (rate * physics.max_power).clamp_min(1e-6)
    ang = heading - torch.asin((across / full_speed).clamp(-1.0, 1.0))
    strong = command(KICK_KIND, physics.max_power, wrap_angle(ang - body), body)
    return choose(reachable, exact, strong)


def freeze_ball(
    pos: Tensor,
    vel: Tensor,
    body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    physics: PhysicsParams,
    rate: Tensor | None = None,
) -> Tensor:
    """Kick that stops the ball where it is (the players' freezeBall).

    The kick opposes the ball's velocity with the power that cancels it (at most the maximum).
    If the ball would then lie outside 0.8 x the kickable distance of the player's next
    position, the ball is instead accelerated towards a point at min(0.7 x kickable distance,
    its distance - 0.1 m) from that position, in its current direction.

    :param rate: the kick power rate, if already known.
    """
    me_next = pos + vel
    if rate is None:
        rate = kick_power_rate(pos, body, ball_pos, physics)
    power = (norm(ball_vel) / rate.clamp_min(1e-6)).clamp(max=physics.max_power)
    against = direction(ball_vel) + math.pi
    stopped = ball_pos + ball_vel + (power * rate).unsqueeze(-1) * unit(against)
    stays = norm(stopped - me_next) < FREEZE_STAYS * physics.kickable_distance
    freeze = command(KICK_KIND, power, wrap_angle(against - body), body)
    offset = ball_pos - me_next
    reach = torch.minimum(
        norm(offset) - FREEZE_PULL_GAP, torch.full_like(power, FREEZE_PULL_REACH * physics.kickable_distance)
    )
    inside = me_next + reach.unsqueeze(-1) * unit(direction(offset))
    pull_in = accelerate_ball_to_velocity(inside - ball_pos, ball_vel, rate, body, physics)
    return choose(stays, freeze, pull_in)


def kick_ball_close_to_body(
    pos: Tensor,
    vel: Tensor,
    body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    global_angle: Tensor,
    ratio: float | Tensor,
    physics: PhysicsParams,
) -> Tensor:
    """Kick that puts the ball next cycle at ``player_size + ball_size + ratio * margin`` from
    the player's next position, in direction ``global_angle`` (kickBallCloseToBody).

    A kick needing more than the maximum power is replaced by :func:`freeze_ball` when the ball
    moves faster than 0.1 m/cycle, and otherwise kicked at the maximum power.
    """
    reach = physics.player_size + physics.ball_size + ratio * physics.kickable_margin
    if isinstance(reach, Tensor):
        reach = reach.unsqueeze(-1)
    spot = pos + vel + reach * unit(global_angle)
    rate = kick_power_rate(pos, body, ball_pos, physics)
    kick = kick_for_acceleration(spot - ball_pos - ball_vel, rate, body)
    too_strong = kick[..., 1] > physics.max_power
    capped = torch.cat((kick[..., :1], kick[..., 1:2].clamp(max=physics.max_power), kick[..., 2:]), dim=-1)
    freeze = too_strong & (norm(ball_vel) > FREEZE_MIN_SPEED)
    if not bool(freeze.any()):  # the common case: skip the freeze kick's arithmetic for every field
        return capped
    return choose(freeze, freeze_ball(pos, vel, body, ball_pos, ball_vel, physics, rate), capped)


def hold_ball(
    pos: Tensor,
    vel: Tensor,
    body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    opp_pos: Tensor,
    ratio: float,
    goal_x: float,
    physics: PhysicsParams,
    opp_body: Tensor | None = None,
    rule: str = "spec",
) -> Tensor:
    """HoldBall for one player per field [B].

    ``rule="spec"``: with an opponent within 5 m of the player, the ball goes to 45 degrees off the
    line nearest opponent -> me, on whichever side of that line the ball already is; otherwise
    straight ahead of the body. If the ball already lies within 0.3 m of that spot and stays
    kickable, the player turns towards the pitch's goal (goal_x, 0) instead of kicking.

    ``rule="reference"`` (BasicPlayer::holdBall(ratio)): the opponent nearest the **ball**, if within
    5 m of it, decides; the ball goes to the side away from that opponent's body heading
    ``opp_body`` [B, M] (iSign = -sign(normalize(body_opp - dir(me - opp))), sign(0) = -1). The turn
    test puts the spot ``ratio`` metres away along the body-relative angle read as a global one
    (the reference's slip), and the turn needs the ball to stay within 0.85 x kickable. With exact,
    every-cycle knowledge of the opponents' heading this rule locks keeper and takers into a loop
    (docs/keepaway.md item 14); with the server's perception it does not.

    The kick is :func:`kick_ball_close_to_body` (which freezes a fast ball it cannot redirect).

    :param opp_pos: opponents [B, M, 2].
    """
    reach = physics.player_size + physics.ball_size + ratio * physics.kickable_margin
    if rule == "reference":
        if opp_body is None:
            raise ValueError("hold_ball(rule='reference') needs the opponents' body angles")
        to_ball = norm(opp_pos - ball_pos.unsqueeze(-2))
        nearest = to_ball.argmin(-1, keepdim=True)
        near_pos = torch.gather(opp_pos, -2, nearest.unsqueeze(-1).expand(-1, 1, 2)).squeeze(-2)
        near_body = torch.gather(opp_body, -1, nearest).squeeze(-1)
        close = torch.gather(to_ball, -1, nearest).squeeze(-1) < HOLD_OPPONENT_RANGE
        away = direction(pos - near_pos)
        side = torch.where(wrap_angle(near_body - away) > 0, -1.0, 1.0)
        relative = wrap_angle(away + side * HOLD_SIDE_ANGLE - body)
        relative = torch.where(close, relative, torch.zeros_like(body))
        angle = wrap_angle(body + relative)
        test_spot = pos + ratio * unit(relative)
    elif rule == "spec":
        opp_dist = norm(opp_pos - pos.unsqueeze(-2))
        nearest = opp_dist.argmin(-1, keepdim=True)
        near_pos = torch.gather(opp_pos, -2, nearest.unsqueeze(-1).expand(-1, 1, 2)).squeeze(-2)
        close = torch.gather(opp_dist, -1, nearest).squeeze(-1) < HOLD_OPPONENT_RANGE
        away = direction(pos - near_pos)
        plus = wrap_angle(away + HOLD_SIDE_ANGLE)
        minus = wrap_angle(away - HOLD_SIDE_ANGLE)
        plus_nearer = norm(pos + reach * unit(plus) - ball_pos) <= norm(pos + reach * unit(minus) - ball_pos)
        angle = torch.where(close, torch.where(plus_nearer, plus, minus), body)
        test_spot = pos + reach * unit(angle)
    else:
        raise ValueError(f"hold_ball rule={rule!r} is invalid; allowed: spec, reference")
    kick = kick_ball_close_to_body(pos, vel, body, ball_pos, ball_vel, angle, ratio, physics)
    goal = torch.tensor([goal_x, 0.0], device=pos.device, dtype=pos.dtype).expand_as(pos)
    turn = face_point(pos, vel, body, goal, physics)
    stays = norm((ball_pos + ball_vel) - (pos + vel)) < HOLD_STAYS * physics.kickable_distance
    return choose((norm(ball_pos - test_spot) < HOLD_SPOT_TOLERANCE) & stays, turn, kick)


def pass_ball(
    pos: Tensor,
    vel: Tensor,
    body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    target: Tensor,
    opponent_near_ball: Tensor,
    physics: PhysicsParams,
) -> Tensor:
    """PassBall for one player per field [B]: kick so the ball reaches ``target`` at 1.2 m/cycle
    (kickTo with the pass end speed).

    If the kick would run the ball into the kicker, the wanted speed is shortened or lengthened
    by the collision distance. A wanted speed above the ball's maximum is kicked anyway when a
    full-power kick already gives more than 85 % of ball_accel_max; a kick needing more than 105 %
    of the maximum power (130 % with an opponent within 2 m of the ball) is not tried. In both
    failing cases the kicker repositions the ball in front of its body instead.
    """
    traj = target - ball_pos
    heading = direction(traj)
    speed = pass_speed(norm(traj), PASS_END_SPEED, physics.ball_decay)
    touch = physics.ball_size + physics.player_size
    along = unit(heading)
    hits_me = norm((pos + vel) - (ball_pos + speed.unsqueeze(-1) * along)) < touch
    proj = dot(pos - ball_pos, along)
    shortened = torch.where(speed < proj, proj - touch, proj + touch)
    speed = torch.where(hits_me, shortened, speed)
    vel_des = speed.unsqueeze(-1) * along
    rate = kick_power_rate(pos, body, ball_pos, physics)
    shoot = accelerate_ball_to_velocity(vel_des, ball_vel, rate, body, physics)
    reposition = kick_ball_close_to_body(pos, vel, body, ball_pos, ball_vel, body, REPOSITION_RATIO, physics)
    full_speed = rate * physics.max_power
    across = -torch.sin(heading) * ball_vel[..., 0] + torch.cos(heading) * ball_vel[..., 1]
    ang = heading - torch.asin((across / full_speed.clamp_min(1e-6)).clamp(-1.0, 1.0))
    best_speed = norm(ball_vel + full_speed.unsqueeze(-1) * unit(ang))
    too_fast_ok = best_speed > WHEN_TO_KICK * physics.ball_accel_max
    needed = norm(vel_des - ball_vel) / rate.clamp_min(1e-6)
    power_ok = (needed <= PASS_POWER_RATIO * physics.max_power) | (
        opponent_near_ball & (needed <= PASS_POWER_RATIO_PRESSED * physics.max_power)
    )
    ok = torch.where(speed > physics.ball_speed_max, too_fast_ok, power_ok)
    return choose(ok, shoot, reposition)


# ------------------------------------------------------------------ GetOpen and BlockPass


def get_open_grid(length: float, width: float, device: torch.device, dtype: torch.dtype) -> Tensor:
    """The 25 GetOpen candidates [25, 2]: a 5 x 5 grid with a 15 % border on each side."""
    xs = torch.linspace(-0.35 * length, 0.35 * length, 5, device=device, dtype=dtype)
    ys = torch.linspace(-0.35 * width, 0.35 * width, 5, device=device, dtype=dtype)
    gx, gy = torch.meshgrid(xs, ys, indexing="ij")
    return torch.stack((gx.reshape(-1), gy.reshape(-1)), dim=-1)


def in_pass_cone(origin: Tensor, end: Tensor, others: Tensor, width: float = CONE_WIDTH) -> Tensor:
    """Whether each of ``others`` [..., K, 2] lies in the pass cone origin -> end [..., 2].

    With q the projection on the line: |other - q| < width |q - origin|, q between the ends, and
    the other closer to the origin than the end is.
    """
    seg = end - origin
    rel = others - origin.unsqueeze(-2)
    return _cone_test(seg[..., 0:1], seg[..., 1:2], rel[..., 0], rel[..., 1], width)


def _cone_test(sx: Tensor, sy: Tensor, rx: Tensor, ry: Tensor, width: float) -> Tensor:
    """Pass-cone test on components (segment s, others r, both relative to the origin).

    With d = r.s and L = |s|^2: off-line distance^2 = |r|^2 - d^2/L, distance along = d/sqrt(L),
    so the cone condition is |r|^2 L < (1 + width^2) d^2 with 0 <= d <= L and |r|^2 < L.
    """
    seg_sq = sx * sx + sy * sy
    along = rx * sx + ry * sy
    rel_sq = rx * rx + ry * ry
    inside = rel_sq * seg_sq < (1.0 + width * width) * along * along
    return inside & (along >= 0.0) & (along <= seg_sq) & (rel_sq < seg_sq)


def get_open_target(
    keeper_pos: Tensor, taker_pos: Tensor, pass_from: Tensor, grid: Tensor, kernels: str = "auto"
) -> Tensor:
    """GetOpen point [B, n, 2] of every keeper: the least congested grid point whose pass cone
    from ``pass_from`` holds no taker (the region centre if none).

    Congestion of a point for keeper k: the sum over all players (in index order) of
    1 / distance, less keeper k's own term. On CPU the fields are processed in blocks so that the
    [25, B, P] temporaries stay in the cache, or by a numba kernel (``kernels``, see
    :func:`resolve_kernels`).
    """
    batch, keepers = keeper_pos.shape[:2]
    candidates = grid.shape[0]
    players = torch.cat((keeper_pos, taker_pos), dim=-2)  # [B, P, 2]
    if resolve_kernels(kernels, keeper_pos.device, keeper_pos.dtype) == "numba":
        from hfrl_torch.envs.keepaway.kernels_numba import least_congested_points

        choice = torch.empty(batch, keepers, dtype=torch.long)
        none_open = torch.empty(batch, dtype=torch.bool)
        consts = torch.tensor([1.0 + CONE_WIDTH * CONE_WIDTH, 1e-12, BLOCKED_PENALTY, 0.0, 1.0])
        least_congested_points(
            grid.contiguous().numpy(),
            players.numpy(),
            pass_from.expand(batch, 2).contiguous().numpy(),
            keepers,
            consts.to(keeper_pos.dtype).numpy(),
            choice.numpy(),
            none_open.numpy(),
        )
        return torch.where(none_open[:, None, None], torch.zeros_like(grid[:1]), grid[choice])
    block = batch if keeper_pos.device.type != "cpu" else INTERCEPT_BLOCK
    gx, gy = grid[:, 0, None, None], grid[:, 1, None, None]  # [25, 1, 1]
    px, py = players[..., 0], players[..., 1]  # [B, P]
    sx = gx[..., 0] - pass_from[:, 0]  # [25, B]
    sy = gy[..., 0] - pass_from[:, 1]
    rx = taker_pos[..., 0] - pass_from[:, 0, None]  # [B, m]
    ry = taker_pos[..., 1] - pass_from[:, 1, None]
    blocked = _cone_test(sx.unsqueeze(-1), sy.unsqueeze(-1), rx, ry, CONE_WIDTH).any(-1)  # [25, B]
    penalty = blocked.unsqueeze(-1).to(keeper_pos.dtype) * BLOCKED_PENALTY
    weights = torch.arange(candidates, 0, -1, device=grid.device, dtype=keeper_pos.dtype)[:, None, None]
    index = torch.empty(batch, keepers, device=grid.device, dtype=keeper_pos.dtype)
    for lo in range(0, batch, block):
        hi = min(lo + block, batch)
        shape = (candidates, hi - lo, players.shape[1])
        inv = _scratch("inv", shape, keeper_pos)
        tmp = _scratch("inv_tmp", shape, keeper_pos)
        torch.sub(gx, px[lo:hi], out=inv)
        inv.mul_(inv)
        torch.sub(gy, py[lo:hi], out=tmp)
        inv.add_(tmp.mul_(tmp)).add_(1e-12).rsqrt_()
        total = _scratch("inv_total", (candidates, hi - lo, 1), keeper_pos)
        total.copy_(inv[..., :1])
        for q in range(1, inv.shape[-1]):  # left to right, as the kernel (torch.sum's order varies)
            total.add_(inv[..., q : q + 1])
        cong = _scratch("cong", (candidates, hi - lo, keepers), keeper_pos)
        torch.sub(total, inv[..., :keepers], out=cong)
        cong.add_(penalty[:, lo:hi])
        best = cong.amin(0)
        torch.mul(cong == best, weights, out=cong)
        torch.amax(cong, 0, out=index[lo:hi])
    point = grid[candidates - index.long()]  # ties go to the first grid point
    none_valid = blocked.all(0)
    return torch.where(none_valid[:, None, None], torch.zeros_like(point), point)


def get_open(
    pos: Tensor, vel: Tensor, body: Tensor, target: Tensor, ball_pos: Tensor, physics: PhysicsParams
) -> Tensor:
    """GetOpen movement: face the ball within 1.5 m of the point, else move there (7 degrees)."""
    move = move_to_point(pos, vel, body, target, WHEN_TO_TURN, physics)
    face = face_point(pos, vel, body, ball_pos, physics)
    return choose(norm(pos - target) < GET_OPEN_BUFFER, face, move)


def block_pass_target(keeper_pos: Tensor, taker_pos: Tensor, with_ball: Tensor, ball_pos: Tensor) -> Tensor:
    """BlockPass point [B, 2]: 4 m from the most open keeper towards the ball (never past it).

    The most open keeper is the one, other than ``with_ball`` [B], with the fewest takers in
    the pass cone from the keeper with the ball (ties: lower index).
    """
    holder = torch.gather(keeper_pos, 1, with_ball[:, None, None].expand(-1, 1, 2)).squeeze(1)
    batch, keepers = keeper_pos.shape[:2]
    origin = holder.unsqueeze(1).expand(-1, keepers, -1).reshape(-1, 2)
    blockers = (
        in_pass_cone(origin, keeper_pos.reshape(-1, 2), taker_pos.repeat_interleave(keepers, dim=0))
        .sum(-1)
        .reshape(batch, keepers)
    )
    blockers = blockers.scatter(1, with_ball.unsqueeze(-1), torch.iinfo(blockers.dtype).max)
    open_keeper = blockers.argmin(-1)
    kpos = torch.gather(keeper_pos, 1, open_keeper[:, None, None].expand(-1, 1, 2)).squeeze(1)
    to_ball = ball_pos - kpos
    step = torch.minimum(norm(to_ball), torch.full_like(to_ball[..., 0], MARK_DISTANCE))
    return kpos + step.unsqueeze(-1) * unit(direction(to_ball))


def block_pass(
    pos: Tensor, vel: Tensor, body: Tensor, target: Tensor, ball_pos: Tensor, physics: PhysicsParams
) -> Tensor:
    """BlockPass movement: face the ball within 2 m of the point, else move there (25 degrees)."""
    move = move_to_point(pos, vel, body, target, MARK_TURN, physics)
    face = face_point(pos, vel, body, ball_pos, physics)
    return choose(norm(pos - target) < MARK_BUFFER, face, move)
