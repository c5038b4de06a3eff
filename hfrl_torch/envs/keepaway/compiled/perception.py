"""perception.py in compiled code: each player's world model under ``perception="server"`` (the see
message's quantisation, the extrapolation between sees, the collision guess after sense_body), per
field and observer, on the state's beliefs ``seen_pos``/``seen_vel``/``seen_body``."""

from __future__ import annotations

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import (
    _F,
    _FA,
    _FI,
    B_DECAY,
    B_RAND,
    B_SIZE,
    B_SPEED,
    DASH_RATE,
    DEG,
    KD,
    MAX_POWER,
    MIN_DASH,
    P_DECAY,
    P_RAND,
    P_SIZE,
    P_SPEED,
    M,
    N,
    _hyp,
    _wrap,
)
from hfrl_torch.envs.keepaway.compiled.physics import _kick_rate
from hfrl_torch.envs.keepaway.perception import (
    BALL_AGREEMENT,
    COLLISION_BALL_BOUNCE,
    COLLISION_BALL_GAP,
    COLLISION_RANGE,
    COLLISION_SLOWDOWN,
    COLLISION_STILL_RANGE,
    DIR_CHG_QSTEP,
    DIST_CHG_QSTEP,
    DIST_QSTEP,
    DIST_ROUND,
    EPS,
    FAR_LENGTH,
    FASTEST_OPPONENT_STEP,
    NO_PLAYER_DISTANCE,
    OPPONENT_DRIFT,
    OPPONENT_FAST_DRIFT,
    OPPONENT_FAST_SPEED,
    PREDICTED_MOVING,
    SEE_CYCLES,
    SENSE_SPEED_QSTEP,
    STILL,
    TOO_FAR_LENGTH,
    TURNED_SPEED,
)
from hfrl_torch.envs.keepaway.physics import DASH_KIND, KICK_KIND, TURN_KIND

QDIST_LOW, QDIST_HIGH = -240, 60  # log(1e-10) is -230 tenths; the field's diagonal is under 400 m


@_F
def _qdist_of(tenths):
    """The quantised distance whose log rounds to ``tenths`` tenths."""
    return np.rint(np.exp(tenths * DIST_QSTEP) / DIST_ROUND) * DIST_ROUND


@_FA
def _quantisation_tables():
    """The sensor's quantised distances for logs of QDIST_LOW..QDIST_HIGH tenths, and cos and sin
    of every whole degree from -180 to 180: made by the same compiled functions as the direct
    computations, so that a lookup gives the same bits."""
    qdist = np.empty(QDIST_HIGH - QDIST_LOW + 1)
    for i in range(qdist.shape[0]):
        qdist[i] = _qdist_of(np.float64(QDIST_LOW + i))
    cos_deg, sin_deg = np.empty(361), np.empty(361)
    for i in range(361):
        a = np.float64(i - 180) * DEG
        cos_deg[i], sin_deg[i] = np.cos(a), np.sin(a)
    return qdist, cos_deg, sin_deg


QDIST, COS_DEG, SIN_DEG = _quantisation_tables()


@_F
def _qdist(d):
    tenths = np.rint(np.log(d + EPS) / DIST_QSTEP)
    if QDIST_LOW <= tenths <= QDIST_HIGH:
        return QDIST[np.int64(tenths) - QDIST_LOW]
    return _qdist_of(tenths)


@_F
def _qdir(a):
    return np.rint(a / DEG) * DEG


@_F
def _observe(b, p, st, u, u0, use_u, prm, ip):
    """perception.observe for observer ``p`` (0-based player) of field ``b``: its belief (holding
    the prior, already extrapolated) replaced by a see of the true state; ``u[u0 + o]`` are the
    withheld-information uniforms."""
    pos, vel, body, spos, svel, sbody = st.pos, st.vel, st.body, st.seen_pos, st.seen_vel, st.seen_body
    n, m = ip[N], ip[M]
    objects = 1 + n + m
    me = 1 + p
    mx, my = pos[b, me, 0], pos[b, me, 1]
    mvx, mvy = vel[b, me, 0], vel[b, me, 1]
    head = body[b, me]
    ch, sh = np.cos(head), np.sin(head)
    qd0 = 0.0
    prior_bvx, prior_bvy = svel[b, p, 0, 0], svel[b, p, 0, 1]
    for o in range(objects):
        if o == me:
            continue
        rx, ry = pos[b, o, 0] - mx, pos[b, o, 1] - my
        dist = _hyp(rx, ry)
        seen = dist > 0
        safe = dist if seen else 1.0
        deg = np.rint(_wrap(np.arctan2(ry, rx) - head) / DEG)  # as _qdir
        qdir = deg * DEG
        qdist = _qdist(dist)
        if o == 0:
            qd0 = qdist
        spos[b, p, o, 0] = mx + qdist * np.cos(head + qdir)
        spos[b, p, o, 1] = my + qdist * np.sin(head + qdir)
        withheld = False
        if use_u:
            far = min(max((qdist - FAR_LENGTH) / (TOO_FAR_LENGTH - FAR_LENGTH), 0.0), 1.0)
            withheld = u[u0 + o] < far and seen
        if withheld:
            continue
        wx, wy = vel[b, o, 0] - mvx, vel[b, o, 1] - mvy
        ex, ey = rx / safe, ry / safe
        dist_chg = wx * ex + wy * ey
        dir_chg = ((wy * ex - wx * ey) / safe) / DEG
        if dir_chg != 0:
            dir_chg = np.rint(dir_chg / DIR_CHG_QSTEP) * DIR_CHG_QSTEP
        qdist_chg = qdist * np.rint((dist_chg / safe) / DIST_CHG_QSTEP) * DIST_CHG_QSTEP
        turn = dir_chg * DEG * qdist
        ca, sa = COS_DEG[np.int64(deg) + 180], SIN_DEG[np.int64(deg) + 180]
        rvx = qdist_chg * ca - turn * sa
        rvy = qdist_chg * sa + turn * ca
        svel[b, p, o, 0] = mvx + (ch * rvx - sh * rvy)
        svel[b, p, o, 1] = mvy + (sh * rvx + ch * rvy)
        sbody[b, p, o] = _wrap(head + _qdir(_wrap(body[b, o] - head)))
    # the ball (calculateStateBall)
    nvx, nvy = svel[b, p, 0, 0], svel[b, p, 0, 1]
    bound = BALL_AGREEMENT * prm[B_RAND] * _hyp(prior_bvx, prior_bvy)
    if abs(nvx - prior_bvx) <= bound and abs(nvy - prior_bvy) <= bound:
        nvx, nvy = 0.5 * (nvx + prior_bvx), 0.5 * (nvy + prior_bvy)
    first, count = (1 + n, m) if p < n else (1, n)
    near = False
    for o in range(first, first + count):
        if _hyp(spos[b, p, o, 0] - spos[b, p, 0, 0], spos[b, p, o, 1] - spos[b, p, 0, 1]) < prm[KD]:
            near = True
    if near and qd0 > prm[KD]:
        nvx, nvy = 0.0, 0.0
    speed = _hyp(nvx, nvy)
    if speed > (1.0 + prm[B_RAND]) * prm[B_SPEED]:
        scale = prm[B_SPEED] / max(speed, 1e-12)
        nvx, nvy = nvx * scale, nvy * scale
    svel[b, p, 0, 0], svel[b, p, 0, 1] = nvx, nvy
    for o in range(1, objects):
        if o == me:
            continue
        speed = _hyp(svel[b, p, o, 0], svel[b, p, o, 1])
        if speed >= (1.0 + prm[P_RAND]) * prm[P_SPEED]:
            scale = prm[P_SPEED] / max(speed, 1e-12)
            svel[b, p, o, 0] = svel[b, p, o, 0] * scale
            svel[b, p, o, 1] = svel[b, p, o, 1] * scale


@_F
def _own_truth(b, p, st):
    """perception.own_truth for observer ``p``: its own entry set to its true state."""
    pos, vel, body, spos, svel, sbody = st.pos, st.vel, st.body, st.seen_pos, st.seen_vel, st.seen_body
    me = 1 + p
    spos[b, p, me, 0], spos[b, p, me, 1] = pos[b, me, 0], pos[b, me, 1]
    svel[b, p, me, 0], svel[b, p, me, 1] = vel[b, me, 0], vel[b, me, 1]
    sbody[b, p, me] = body[b, me]


@_F
def _extrapolate(b, p, kax, kay, kicked, st, prm, ip):
    """perception.extrapolate for observer ``p``: its belief one cycle on, in place; (kax, kay)
    is the acceleration its own kick should give the believed ball."""
    spos, svel = st.seen_pos, st.seen_vel
    n, m = ip[N], ip[M]
    bx, by = spos[b, p, 0, 0], spos[b, p, 0, 1]
    bvx, bvy = svel[b, p, 0, 0], svel[b, p, 0, 1]
    if p < n:
        mates, count_mates, opps, count_opps = 1, n, 1 + n, m
    else:
        mates, count_mates, opps, count_opps = 1 + n, m, 1, n
    if kicked:
        kvx, kvy = bvx + kax, bvy + kay
        speed = _hyp(kvx, kvy)
        scale = min(prm[B_SPEED] / max(speed, 1e-12), 1.0)
        kvx, kvy = kvx * scale, kvy * scale
        nbx, nby = bx + kvx, by + kvy
        nvx, nvy = kvx * prm[B_DECAY], kvy * prm[B_DECAY]
    else:
        best, ax, ay = np.inf, 0.0, 0.0
        for o in range(opps, opps + count_opps):
            d = _hyp(spos[b, p, o, 0] - bx, spos[b, p, o, 1] - by)
            if d < best:
                best, ax, ay = d, spos[b, p, o, 0], spos[b, p, o, 1]
        nbx, nby = bx + bvx, by + bvy
        nvx, nvy = bvx * prm[B_DECAY], bvy * prm[B_DECAY]
        if _hyp(nbx - ax, nby - ay) < prm[KD]:
            nvx, nvy = 0.0, 0.0
    spos[b, p, 0, 0], spos[b, p, 0, 1] = nbx, nby
    svel[b, p, 0, 0], svel[b, p, 0, 1] = nvx, nvy
    for o in range(mates + 1, mates + count_mates):  # the team's first player stays where it was seen
        spos[b, p, o, 0] = spos[b, p, o, 0] + svel[b, p, o, 0]
        spos[b, p, o, 1] = spos[b, p, o, 1] + svel[b, p, o, 1]
        svel[b, p, o, 0] = svel[b, p, o, 0] * prm[P_DECAY]
        svel[b, p, o, 1] = svel[b, p, o, 1] * prm[P_DECAY]
    best, fastest = np.inf, opps
    for o in range(opps, opps + count_opps):
        d = _hyp(nbx - spos[b, p, o, 0], nby - spos[b, p, o, 1])
        if d < best:
            best, fastest = d, o
    if nvx > 0:
        drift = OPPONENT_FAST_DRIFT if nvx > OPPONENT_FAST_SPEED else OPPONENT_DRIFT
    else:
        drift = -OPPONENT_FAST_DRIFT if nvx < -OPPONENT_FAST_SPEED else -OPPONENT_DRIFT
    for o in range(opps, opps + count_opps):
        if o == fastest:
            d = np.arctan2(nby - spos[b, p, o, 1], nbx - spos[b, p, o, 0])
            spos[b, p, o, 0] = spos[b, p, o, 0] + FASTEST_OPPONENT_STEP * np.cos(d)
            spos[b, p, o, 1] = spos[b, p, o, 1] + FASTEST_OPPONENT_STEP * np.sin(d)
        else:
            spos[b, p, o, 0] = spos[b, p, o, 0] + drift
        svel[b, p, o, 0] = svel[b, p, o, 0] * prm[P_DECAY]
        svel[b, p, o, 1] = svel[b, p, o, 1] * prm[P_DECAY]


@_F
def _nearest_other(b, p, st, players, prm):
    """The distance from observer ``p`` to the nearest other player in its belief (1000 if none, as
    ``getClosestInSetTo``), or -1 when its believed ball is too far for a collision this cycle: the
    ball must end within 1.585 m, it moves less than 2 B_SPEED in a cycle (a seen velocity is capped
    near B_SPEED) and the player at most P_SPEED."""
    pos, spos = st.pos, st.seen_pos
    o = 1 + p
    reach = prm[KD] + COLLISION_RANGE + 2.0 * prm[B_SPEED] + prm[P_SPEED]
    if _hyp(spos[b, p, 0, 0] - pos[b, o, 0], spos[b, p, 0, 1] - pos[b, o, 1]) >= reach:
        return -1.0
    nearest = NO_PLAYER_DISTANCE
    for q in range(players):
        if q != p:
            nearest = min(
                nearest, _hyp(spos[b, p, 1 + q, 0] - pos[b, o, 0], spos[b, p, 1 + q, 1] - pos[b, o, 1])
            )
    return nearest


@_F
def _after_collision(b, p, st, cmd, new_vel, new_body, nearest, prm):
    """perception.after_collision for observer ``p``, in place: ``pos``, ``vel``, ``body`` still hold
    the state before the cycle, ``new_vel`` [O, 2] and ``new_body`` [O] the one after it (reported as
    sense_body does); ``nearest`` is :func:`_nearest_other` (-1: no collision possible)."""
    if nearest < 0.0:
        return
    pos, vel, body, spos, svel = st.pos, st.vel, st.body, st.seen_pos, st.seen_vel
    o = 1 + p
    kind = np.int64(cmd[p, 0])
    px, py, vx, vy = pos[b, o, 0], pos[b, o, 1], vel[b, o, 0], vel[b, o, 1]
    if kind in (DASH_KIND, TURN_KIND):
        if kind == DASH_KIND:
            pw = min(max(cmd[p, 1], prm[MIN_DASH]), prm[MAX_POWER]) * prm[DASH_RATE]
            vx, vy = vx + pw * np.cos(body[b, o]), vy + pw * np.sin(body[b, o])
        scale = min(prm[P_SPEED] / max(_hyp(vx, vy), 1e-12), 1.0)
        vx, vy = vx * scale, vy * scale
        px, py = px + vx, py + vy
        vx, vy = vx * prm[P_DECAY], vy * prm[P_DECAY]
    bx, by = spos[b, p, 0, 0], spos[b, p, 0, 1]
    d_ball = _hyp(bx - px, by - py)
    if d_ball >= prm[KD] + COLLISION_RANGE or d_ball >= nearest:  # no test passes, or another is blamed
        return
    nb = new_body[o]
    sensed = np.rint(_hyp(new_vel[o, 0], new_vel[o, 1]) / SENSE_SPEED_QSTEP) * SENSE_SPEED_QSTEP
    heading = nb + _qdir(_wrap(np.arctan2(new_vel[o, 1], new_vel[o, 0]) - nb))
    sx, sy = sensed * np.cos(heading), sensed * np.sin(heading)
    predicted = _hyp(vx, vy)
    still = sensed < STILL
    turned = ((vx > 0) != (sx > 0) or abs(vx) < TURNED_SPEED) and (
        (vy > 0) != (sy > 0) or abs(vy) < TURNED_SPEED
    )
    collided = (
        (still and predicted > PREDICTED_MOVING and d_ball < COLLISION_STILL_RANGE)
        or (still and d_ball < prm[P_SIZE] + prm[B_SIZE])
        or (
            d_ball < prm[KD] + COLLISION_RANGE
            and not still
            and turned
            and sensed < COLLISION_SLOWDOWN * predicted
        )
    )
    if collided and d_ball < nearest:
        a = np.arctan2(by - py, bx - px)
        spos[b, p, 0, 0] = px + COLLISION_BALL_GAP * np.cos(a)
        spos[b, p, 0, 1] = py + COLLISION_BALL_GAP * np.sin(a)
        svel[b, p, 0, 0] = COLLISION_BALL_BOUNCE * svel[b, p, 0, 0]
        svel[b, p, 0, 1] = COLLISION_BALL_BOUNCE * svel[b, p, 0, 1]


@_F
def _sees(clock, phase):
    return (clock + phase) % SEE_CYCLES != SEE_CYCLES - 1


@_FI
def _predict_beliefs(b, st, cmd, new_vel, new_body, prm, ip):
    """Every player's world model of field ``b`` one cycle on (perception.extrapolate from the own
    command ``cmd`` [P, 3], then perception.after_collision), in place; the state still holds the
    cycle's start, ``new_vel`` [O, 2] and ``new_body`` [O] its end."""
    pos, body, spos = st.pos, st.body, st.seen_pos
    kd = prm[KD]
    players = ip[N] + ip[M]
    for p in range(players):
        o = 1 + p
        kax, kay, kicked = 0.0, 0.0, False
        if np.int64(cmd[p, 0]) == KICK_KIND:
            px, py, pb = pos[b, o, 0], pos[b, o, 1], body[b, o]
            sbx, sby = spos[b, p, 0, 0], spos[b, p, 0, 1]
            rx, ry = sbx - px, sby - py
            dist = _hyp(rx, ry)
            kicked = dist < kd
            if dist <= kd:
                pw = min(max(cmd[p, 1], 0.0), prm[MAX_POWER])
                rate = _kick_rate(px, py, pb, sbx, sby, prm)
                kax = pw * rate * np.cos(pb + cmd[p, 2])
                kay = pw * rate * np.sin(pb + cmd[p, 2])
        nearest = _nearest_other(b, p, st, players, prm)  # before the extrapolation
        _extrapolate(b, p, kax, kay, kicked, st, prm, ip)
        _after_collision(b, p, st, cmd, new_vel, new_body, nearest, prm)


@_FI
def _see(b, st, u, u_seen, prm, ip):
    """The see messages of field ``b``'s cycle just ended: each player whose phase sees now observes
    the true state (withheld information drawn from ``u[u_seen:]``, one uniform per player and object);
    every player's own entry set to the truth."""
    players = ip[N] + ip[M]
    objects = 1 + players
    for p in range(players):
        if _sees(st.clock[b], st.see_phase[b, p]):
            _observe(b, p, st, u, u_seen + p * objects, True, prm, ip)
        _own_truth(b, p, st)
