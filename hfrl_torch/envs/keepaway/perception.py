"""What each player knows under ``perception="server"``: the server's see message every 150 ms
(rcssserver 19, ``VisualSenderPlayerV8``, the keepaway script's 360-degree normal view) and the UT
keepaway players' world model in between (``WorldModel::updateAfterSenseMessage`` /
``updateAfterSeeMessage``).

A belief is, for every field b, observer p (the players, keepers first) and object o (ball, keepers,
takers, as in the state), a position [B, P, O, 2], a velocity [B, P, O, 2] and a body angle
[B, P, O]. The observer's own entry is always the true state (sense_body every cycle; the players'
self-localisation error is not modelled). docs/keepaway.md ("Fidelity") gives the sources line by line.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.params import PhysicsParams
from hfrl_torch.envs.keepaway.physics import (
    DASH_KIND,
    TURN_KIND,
    clip_norm,
    dash_acceleration,
    direction,
    norm,
    unit,
    wrap_angle,
)

SEE_CYCLES = 3  # a see every 150 ms: two of every three 100 ms cycles carry one
EPS = 1e-10  # rcssserver's EPS inside the log of the distance quantisation
DIST_QSTEP = 0.1  # quantize_step (players and ball)
DIST_ROUND = 0.1  # the final rounding of every reported distance
DIST_CHG_QSTEP = 0.02  # dist_chg / distance is quantised to 0.02
DIR_CHG_QSTEP = 0.1  # dir_chg in degrees (dirQStep with the normal view's noise term 1)
FAR_LENGTH = 20.0  # unum_far_length and ball_vel_far_length
TOO_FAR_LENGTH = 40.0  # unum_too_far_length and ball_vel_too_far_length
FASTEST_OPPONENT_STEP = 0.3  # the world model moves the opponent fastest to the ball this far towards it
OPPONENT_DRIFT = 0.25  # ... and every other opponent this far along x, with the ball's x velocity
OPPONENT_FAST_DRIFT = 0.5  # ... or this far when the ball moves faster than 1 m/cycle along x
SENSE_SPEED_QSTEP = 0.01  # sense_body's speed is quantised to this (BodySenderPlayerV6::sendVelocity)
STILL = 1e-4  # Trilearn's EPSILON: a sensed speed below it tells nothing of a collision's direction
COLLISION_BALL_GAP = 0.2  # where the world model puts a ball it believes the observer ran into
COLLISION_BALL_BOUNCE = -0.1  # ... and the factor on its velocity
COLLISION_RANGE = 0.5  # a collision is considered with the ball within kickable distance + this
COLLISION_STILL_RANGE = 0.8  # ... or within this of a still player whose prediction moved
PREDICTED_MOVING = 0.01  # a predicted speed above this counts as moving
TURNED_SPEED = 0.08  # a predicted velocity axis below this counts as turned (reversed)
COLLISION_SLOWDOWN = 0.25  # ... and a sensed speed under this share of the predicted one as stopped
NO_PLAYER_DISTANCE = 1000.0  # getClosestInSetTo's distance when the set is empty
BALL_AGREEMENT = 2.0  # seen and prior ball velocities agree within this many ball_rand |v| per axis
OPPONENT_FAST_SPEED = 1.0  # the ball's x speed above which the opponents drift OPPONENT_FAST_DRIFT


def sees_now(clock: Tensor, phase: Tensor) -> Tensor:
    """Whether each player [B, P] gets a see message in server cycle ``clock`` [B]: every 150 ms,
    i.e. in the cycles c with (c + phase) mod 3 != 2 (the players synchronise their sees to the
    start of a cycle, SenseHandler::synchronize; the phase is the player's own)."""
    return (clock.unsqueeze(-1) + phase) % SEE_CYCLES != SEE_CYCLES - 1


def quantise_distance(dist: Tensor) -> Tensor:
    """The distance a see message reports: round(exp(round(log(d + EPS), 0.1)), 0.1)."""
    qlog = torch.round(torch.log(dist + EPS) / DIST_QSTEP) * DIST_QSTEP
    return torch.round(torch.exp(qlog) / DIST_ROUND) * DIST_ROUND


def quantise_direction(angle: Tensor) -> Tensor:
    """An angle (radians, in [-pi, pi)) rounded to whole degrees as the server reports it (rint)."""
    return torch.deg2rad(torch.round(torch.rad2deg(angle)))


def _team_slices(keepers: int, objects: int) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """(own team, opponents) object slices for keeper observers and for taker observers."""
    keeper_objects, taker_objects = slice(1, 1 + keepers), slice(1 + keepers, objects)
    return (keeper_objects, taker_objects), (taker_objects, keeper_objects)


def observe(
    pos: Tensor,
    vel: Tensor,
    body: Tensor,
    prior_pos: Tensor,
    prior_vel: Tensor,
    prior_body: Tensor,
    keepers: int,
    physics: PhysicsParams,
    uniforms: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Every player's belief right after a see message of the true state ``pos``/``vel`` [B, O, 2],
    ``body`` [B, O] (object 0 the ball).

    Each object's distance is quantised (:func:`quantise_distance`) and its direction from the
    observer's head (aligned with its body) rounded to a degree; velocity comes from the quantised
    distance and direction changes (dist_chg / distance to 0.02, dir_chg to 0.1 degree) and a
    player's body direction is rounded to a degree, as ``calculateVelocityDynamicObject`` and
    ``updateDynamicObjectAfterSee`` rebuild them. Beyond 20 m that information is withheld with
    probability (d - 20) / 20 (the object's prior velocity and body are kept). The ball's velocity is
    averaged with the prior one when they agree within 2 ball_rand |v| per axis, zeroed when an
    opponent can kick the ball that the observer cannot, and capped like ``calculateStateBall``;
    a player's speed is capped like ``calculateStatePlayer``.

    :param prior_pos: the beliefs [B, P, O, 2] just before the see (``prior_vel`` alike,
        ``prior_body`` [B, P, O]).
    :param uniforms: U(0, 1) [B, P, O] for the withheld information (``None``: never withheld).
    :returns: the new beliefs (position, velocity, body).
    """
    objects = pos.shape[1]
    me_pos, me_vel, me_body = pos[:, 1:], vel[:, 1:], body[:, 1:]  # [B, P, ...]
    rel = pos.unsqueeze(1) - me_pos.unsqueeze(2)  # [B, P, O, 2]
    dist = norm(rel)
    seen = dist > 0
    safe = torch.where(seen, dist, torch.ones_like(dist))
    qdir = quantise_direction(wrap_angle(direction(rel) - me_body.unsqueeze(-1)))
    qdist = quantise_distance(dist)
    head = me_body.unsqueeze(-1)
    seen_pos = me_pos.unsqueeze(2) + qdist.unsqueeze(-1) * unit(head + qdir)

    vrel = vel.unsqueeze(1) - me_vel.unsqueeze(2)
    ex, ey = rel[..., 0] / safe, rel[..., 1] / safe
    dist_chg = vrel[..., 0] * ex + vrel[..., 1] * ey
    dir_chg = torch.rad2deg((vrel[..., 1] * ex - vrel[..., 0] * ey) / safe)
    qdir_chg = torch.where(dir_chg == 0, dir_chg, torch.round(dir_chg / DIR_CHG_QSTEP) * DIR_CHG_QSTEP)
    qdist_chg = qdist * torch.round((dist_chg / safe) / DIST_CHG_QSTEP) * DIST_CHG_QSTEP
    turn = torch.deg2rad(qdir_chg) * qdist
    cos_a, sin_a = torch.cos(qdir), torch.sin(qdir)
    rel_v = torch.stack((qdist_chg * cos_a - turn * sin_a, qdist_chg * sin_a + turn * cos_a), -1)
    cos_h, sin_h = torch.cos(head), torch.sin(head)
    seen_vel = me_vel.unsqueeze(2) + torch.stack(
        (cos_h * rel_v[..., 0] - sin_h * rel_v[..., 1], sin_h * rel_v[..., 0] + cos_h * rel_v[..., 1]), -1
    )
    seen_body = wrap_angle(head + quantise_direction(wrap_angle(body.unsqueeze(1) - head)))
    if uniforms is not None:
        far = ((qdist - FAR_LENGTH) / (TOO_FAR_LENGTH - FAR_LENGTH)).clamp(0.0, 1.0)
        withheld = (uniforms < far) & seen
        seen_vel = torch.where(withheld.unsqueeze(-1), prior_vel, seen_vel)
        seen_body = torch.where(withheld, prior_body, seen_body)

    # the ball (calculateStateBall)
    ball_new, ball_prior = seen_vel[:, :, 0], prior_vel[:, :, 0]
    bound = BALL_AGREEMENT * physics.ball_rand * norm(ball_prior)
    agree = ((ball_new - ball_prior).abs() <= bound.unsqueeze(-1)).all(-1)
    ball_v = torch.where(agree.unsqueeze(-1), 0.5 * (ball_new + ball_prior), ball_new)
    kd = physics.kickable_distance
    opp_near = []
    observers = (slice(0, keepers), slice(keepers, None))
    for (_, opponents), obs in zip(_team_slices(keepers, objects), observers, strict=True):
        ball_seen = seen_pos[:, obs, 0].unsqueeze(2)
        opp_near.append((norm(seen_pos[:, obs, opponents] - ball_seen) < kd).any(-1))
    frozen = torch.cat(opp_near, 1) & (qdist[:, :, 0] > kd)
    ball_v = torch.where(frozen.unsqueeze(-1), torch.zeros_like(ball_v), ball_v)
    speed = norm(ball_v)
    too_fast = speed > (1.0 + physics.ball_rand) * physics.ball_speed_max
    capped = ball_v * (physics.ball_speed_max / speed.clamp_min(1e-12)).unsqueeze(-1)
    ball_v = torch.where(too_fast.unsqueeze(-1), capped, ball_v)
    # the players (calculateStatePlayer)
    player_v = seen_vel[:, :, 1:]
    speed = norm(player_v)
    too_fast = speed >= (1.0 + physics.player_rand) * physics.player_speed_max
    player_v = torch.where(
        too_fast.unsqueeze(-1),
        player_v * (physics.player_speed_max / speed.clamp_min(1e-12)).unsqueeze(-1),
        player_v,
    )
    seen_vel = torch.cat((ball_v.unsqueeze(2), player_v), 2)
    return own_truth(seen_pos, seen_vel, seen_body, pos, vel, body)


def own_truth(
    belief_pos: Tensor, belief_vel: Tensor, belief_body: Tensor, pos: Tensor, vel: Tensor, body: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """Beliefs with each observer's own entry set to its true state."""
    players = belief_pos.shape[1]
    objects = torch.arange(belief_pos.shape[2], device=pos.device)
    me = objects == torch.arange(1, players + 1, device=pos.device).unsqueeze(-1)  # [P, O]
    own = me.unsqueeze(0)
    return (
        torch.where(own.unsqueeze(-1), pos.unsqueeze(1), belief_pos),
        torch.where(own.unsqueeze(-1), vel.unsqueeze(1), belief_vel),
        torch.where(own, body.unsqueeze(1), belief_body),
    )


def extrapolate(
    belief_pos: Tensor,
    belief_vel: Tensor,
    belief_body: Tensor,
    kick_accel: Tensor,
    kicked: Tensor,
    keepers: int,
    physics: PhysicsParams,
) -> tuple[Tensor, Tensor, Tensor]:
    """Every player's world model one cycle on, without a see (``updateAfterSenseMessage``).

    * The ball: after the observer's own kick, where that kick should send it (the command's
      acceleration ``kick_accel`` [B, P, 2] from the believed ball, no noise, speed capped:
      ``updateBallAfterKick``); otherwise it rolls on with its velocity decaying, and stops if the
      opponent nearest the ball could then kick it.
    * Teammates roll on with their velocity decaying, except the team's first player (the world
      model treats number 1 as a goalie and leaves it where it was last seen).
    * Opponents: the one nearest the ball steps 0.3 m towards it; every other one moves 0.25 m
      (0.5 m when the ball's x velocity exceeds 1 m/cycle) along x in the direction of the ball's x
      velocity (the soccer heuristics of ``updateDynamicObjectForNextCycle``); their velocity decays.
    * Body angles stay as last seen.

    :param kicked: [B, P] the observer kicked last cycle with the ball kickable in its belief.
    :returns: the predicted beliefs (own entries are the caller's to set).
    """
    objects = belief_pos.shape[2]
    ball_pos, ball_vel = belief_pos[:, :, 0], belief_vel[:, :, 0]
    kv = clip_norm(ball_vel + kick_accel, physics.ball_speed_max)
    rolled_pos, rolled_vel = ball_pos + ball_vel, ball_vel * physics.ball_decay
    kd = physics.kickable_distance
    new_pos, new_vel = [], []
    observers = (slice(0, keepers), slice(keepers, None))
    for (mates, opponents), obs in zip(_team_slices(keepers, objects), observers, strict=True):
        opp_pos = belief_pos[:, obs, opponents]  # [B, p, k, 2]
        nearest = norm(opp_pos - ball_pos[:, obs].unsqueeze(2)).argmin(-1, keepdim=True)
        opp_at = torch.gather(opp_pos, 2, nearest.unsqueeze(-1).expand(-1, -1, 1, 2)).squeeze(2)
        stops = norm(rolled_pos[:, obs] - opp_at) < kd
        r_vel = torch.where(stops.unsqueeze(-1), torch.zeros_like(rolled_vel[:, obs]), rolled_vel[:, obs])
        hit = kicked[:, obs].unsqueeze(-1)
        b_pos = torch.where(hit, ball_pos[:, obs] + kv[:, obs], rolled_pos[:, obs])
        b_vel = torch.where(hit, kv[:, obs] * physics.ball_decay, r_vel)
        # teammates: roll out, except the team's first player
        m_pos, m_vel = belief_pos[:, obs, mates], belief_vel[:, obs, mates]
        first = torch.zeros(m_pos.shape[2], dtype=torch.bool, device=m_pos.device)
        first[0] = True
        m_new_pos = torch.where(first[:, None], m_pos, m_pos + m_vel)
        m_new_vel = torch.where(first[:, None], m_vel, m_vel * physics.player_decay)
        # opponents: the one nearest the (new) ball towards it, the others drift along x
        o_pos, o_vel = belief_pos[:, obs, opponents], belief_vel[:, obs, opponents]
        to_ball = b_pos.unsqueeze(2) - o_pos
        fastest = torch.arange(o_pos.shape[2], device=o_pos.device) == norm(to_ball).argmin(-1, keepdim=True)
        vx = b_vel[..., 0].unsqueeze(-1)
        drift = torch.where(
            vx > 0,
            torch.where(vx > OPPONENT_FAST_SPEED, OPPONENT_FAST_DRIFT, OPPONENT_DRIFT),
            torch.where(vx < -OPPONENT_FAST_SPEED, -OPPONENT_FAST_DRIFT, -OPPONENT_DRIFT),
        ).expand_as(fastest)
        shift = torch.where(
            fastest.unsqueeze(-1),
            FASTEST_OPPONENT_STEP * unit(direction(to_ball)),
            torch.stack((drift, torch.zeros_like(drift)), -1),
        )
        o_new_pos, o_new_vel = o_pos + shift, o_vel * physics.player_decay
        team_first = obs.start == 0
        parts_pos = (m_new_pos, o_new_pos) if team_first else (o_new_pos, m_new_pos)
        parts_vel = (m_new_vel, o_new_vel) if team_first else (o_new_vel, m_new_vel)
        new_pos.append(torch.cat((b_pos.unsqueeze(2), *parts_pos), 2))
        new_vel.append(torch.cat((b_vel.unsqueeze(2), *parts_vel), 2))
    return torch.cat(new_pos, 1), torch.cat(new_vel, 1), belief_body


def sensed_velocity(vel: Tensor, body: Tensor) -> Tensor:
    """A player's velocity as sense_body reports it and the world model rotates it back: the speed
    quantised to 0.01 m/cycle, the direction rounded to a degree from the body (neck aligned)."""
    speed = torch.round(norm(vel) / SENSE_SPEED_QSTEP) * SENSE_SPEED_QSTEP
    return speed.unsqueeze(-1) * unit(body + quantise_direction(wrap_angle(direction(vel) - body)))


def after_collision(
    belief_pos: Tensor,
    belief_vel: Tensor,
    prior_pos: Tensor,
    me_pos: Tensor,
    me_vel: Tensor,
    me_body: Tensor,
    kind: Tensor,
    power: Tensor,
    sensed_vel: Tensor,
    sensed_body: Tensor,
    physics: PhysicsParams,
) -> tuple[Tensor, Tensor]:
    """The ball in every world model once the sense_body message shows whether the observer ran into it
    (``updateAgentAndBallAfterSense``): the own position and velocity predicted from last cycle's
    command (a dash or turn moves the player, a kick or nothing leaves it), compared with the velocity
    sense_body reports (:func:`sensed_velocity` of the true one, ``sensed_vel`` [B, P, 2], with the body
    ``sensed_body`` [B, P] after the cycle). A collision is assumed when the sensed speed is below 1e-4 with
    the believed ball within 0.8 m of a moving player or inside the player, or, within 1.585 m, when in
    each axis the sensed sign differs from the predicted (or the prediction is under 0.08) and the sensed
    speed is under a quarter of the predicted; if the ball
    is then nearer than every other player (``prior_pos`` [B, P, O, 2], last cycle's beliefs), the
    world model puts it 0.2 m from the player on its side with -0.1 times its velocity
    (``updateBallForCollision``).

    :param belief_pos: the extrapolated beliefs [B, P, O, 2] (``belief_vel`` alike); only the ball
        (object 0) changes.
    :param me_pos: each observer's true state before the cycle [B, P, 2] (``me_vel`` alike, ``me_body``
        [B, P]); ``kind`` and ``power`` [B, P] are its last command.
    :returns: the ball-corrected beliefs (position, velocity).
    """
    moved = (kind == DASH_KIND) | (kind == TURN_KIND)
    dash = torch.where(kind == DASH_KIND, power, torch.zeros_like(power))
    v = clip_norm(me_vel + dash_acceleration(me_body, dash, physics), physics.player_speed_max)
    own_pos = torch.where(moved.unsqueeze(-1), me_pos + v, me_pos)
    own_vel = torch.where(moved.unsqueeze(-1), v * physics.player_decay, me_vel)
    sensed_vel = sensed_velocity(sensed_vel, sensed_body)
    ball, ball_vel = belief_pos[:, :, 0], belief_vel[:, :, 0]
    to_ball = ball - own_pos
    d_ball = norm(to_ball)
    sensed, predicted = norm(sensed_vel), norm(own_vel)
    still = sensed < STILL

    def turned(axis: int) -> Tensor:
        a, b = own_vel[..., axis], sensed_vel[..., axis]
        return ((a > 0) != (b > 0)) | (a.abs() < TURNED_SPEED)

    collided = (
        (still & (predicted > PREDICTED_MOVING) & (d_ball < COLLISION_STILL_RANGE))
        | (still & (d_ball < physics.player_size + physics.ball_size))
        | (
            (d_ball < physics.kickable_distance + COLLISION_RANGE)
            & ~still
            & turned(0)
            & turned(1)
            & (sensed < COLLISION_SLOWDOWN * predicted)
        )
    )
    players = prior_pos.shape[1]
    others = norm(prior_pos[:, :, 1:] - me_pos.unsqueeze(2))  # [B, P, P]
    self_mask = torch.eye(players, dtype=torch.bool, device=me_pos.device)
    nearest = torch.where(self_mask, torch.full_like(others, NO_PLAYER_DISTANCE), others).amin(-1)
    hit = (collided & (d_ball < nearest)).unsqueeze(-1)
    placed = own_pos + COLLISION_BALL_GAP * unit(direction(to_ball))
    new_pos, new_vel = belief_pos.clone(), belief_vel.clone()
    new_pos[:, :, 0] = torch.where(hit, placed, ball)
    new_vel[:, :, 0] = torch.where(hit, COLLISION_BALL_BOUNCE * ball_vel, ball_vel)
    return new_pos, new_vel


def see_phases(batch: int, players: int, generator: torch.Generator, device: torch.device) -> Tensor:
    """Each player's see phase [B, P] in {0, 1, 2}, drawn once (players stay connected across
    episodes, so their see timing relative to the cycle does too)."""
    return torch.randint(0, SEE_CYCLES, (batch, players), generator=generator, device=device)
