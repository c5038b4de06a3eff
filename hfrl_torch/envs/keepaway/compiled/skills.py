"""skills.py in compiled code, per player on a view (positions [O, 2], velocities [O, 2], bodies [O] of
the ball, the keepers and the takers as some player sees them): the turn and dash primitives, the kicks
(HoldBall, PassBall, freezing), interception with look-ahead, GetOpen and BlockPass. A command is a
tuple (kind, power, angle) as skills.command's rows; the skills' constants are skills.py's."""

from __future__ import annotations

import math

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import (
    _F,
    _FI,
    B_ACC,
    B_DECAY,
    B_SIZE,
    B_SPEED,
    CRUISE,
    DASH_ACC,
    DASH_RATE,
    HORIZON,
    INERTIA,
    KD,
    MARGIN,
    MAX_MOMENT,
    MAX_POWER,
    MIN_DASH,
    O_BLOCKED,
    O_GX,
    O_GY,
    O_HELD,
    O_MINE,
    O_TOTAL,
    P_DECAY,
    P_SIZE,
    P_SPEED,
    PI,
    REFERENCE_HOLD,
    T_CRUISE,
    T_REACH,
    T_SERIES,
    T_TRAVEL,
    M,
    N,
    _hyp,
    _wrap,
)
from hfrl_torch.envs.keepaway.compiled.physics import _kick_rate
from hfrl_torch.envs.keepaway.keepers import PASS_OPPONENT_RANGE
from hfrl_torch.envs.keepaway.physics import DASH_KIND, KICK_KIND, TURN_KIND
from hfrl_torch.envs.keepaway.skills import (
    BLOCKED_PENALTY,
    CONE_WIDTH,
    FREEZE_MIN_SPEED,
    FREEZE_PULL_GAP,
    FREEZE_PULL_REACH,
    FREEZE_STAYS,
    HOLD_OPPONENT_RANGE,
    HOLD_SIDE_ANGLE,
    HOLD_SPOT_TOLERANCE,
    HOLD_STAYS,
    INTERCEPT_BEHIND_DISTANCE,
    INTERCEPT_FACE_DISTANCE,
    INTERCEPT_FAR,
    INTERCEPT_LATERAL_FAR,
    INTERCEPT_LATERAL_MID,
    INTERCEPT_LATERAL_NEAR,
    INTERCEPT_MID,
    MARK_DISTANCE,
    PASS_END_SPEED,
    PASS_POWER_RATIO,
    PASS_POWER_RATIO_PRESSED,
    REPOSITION_RATIO,
    WHEN_TO_KICK,
    WHEN_TO_TURN,
)

COS_WHEN_TO_TURN = math.cos(min(WHEN_TO_TURN, math.pi))
CONE_FACTOR = 1.0 + CONE_WIDTH * CONE_WIDTH  # skills._cone_test's (1 + width^2)


@_FI
def _face(px, py, vx, vy, body, tx, ty, prm):
    err = _wrap(np.arctan2(ty - (py + vy), tx - (px + vx)) - body)
    moment = err * (1.0 + prm[INERTIA] * _hyp(vx, vy))
    moment = min(max(moment, -prm[MAX_MOMENT]), prm[MAX_MOMENT])
    return TURN_KIND, 0.0, moment


@_FI
def _dash_power(px, py, vx, vy, body, tx, ty, prm):
    hx, hy = np.cos(body), np.sin(body)
    wanted = min((tx - px) * hx + (ty - py) * hy, prm[P_SPEED])
    accel = wanted - (vx * hx + vy * hy)
    return min(max(accel / prm[DASH_RATE], prm[MIN_DASH]), prm[MAX_POWER])


@_FI
def _move_to(px, py, vx, vy, body, tx, ty, threshold, prm):
    rx = px + vx / (1.0 - prm[P_DECAY])
    ry = py + vy / (1.0 - prm[P_DECAY])
    err = _wrap(np.arctan2(ty - ry, tx - rx) - body)
    if abs(err) > threshold:
        return _face(px, py, vx, vy, body, tx, ty, prm)
    return DASH_KIND, _dash_power(px, py, vx, vy, body, tx, ty, prm), 0.0


@_FI
def _intercept_move(px, py, vx, vy, body, tx, ty, bx, by, prm):
    """skills.intercept_move."""
    kd = prm[KD]
    rx = tx - (px + vx / (1.0 - prm[P_DECAY]))
    ry = ty - (py + vy / (1.0 - prm[P_DECAY]))
    if _hyp(rx, ry) < INTERCEPT_FACE_DISTANCE:
        return _face(px, py, vx, vy, body, bx, by, prm)
    hx, hy = np.cos(body), np.sin(body)
    lateral = abs(hx * ry - hy * rx)
    far = _hyp(tx - px, ty - py)
    ratio = (
        INTERCEPT_LATERAL_FAR
        if far > INTERCEPT_FAR
        else (INTERCEPT_LATERAL_MID if far > INTERCEPT_MID else INTERCEPT_LATERAL_NEAR)
    )
    err = _wrap(np.arctan2(ry, rx) - body)
    behind = _hyp(rx, ry) > INTERCEPT_BEHIND_DISTANCE and abs(err) > 0.5 * PI
    if (lateral > ratio * kd or behind) and abs(err) > WHEN_TO_TURN:
        return _face(px, py, vx, vy, body, tx, ty, prm)
    return DASH_KIND, _dash_power(px, py, vx, vy, body, tx, ty, prm), 0.0


@_F
def _kick_for(ax, ay, rate, body):
    return KICK_KIND, _hyp(ax, ay) / max(rate, 1e-6), _wrap(np.arctan2(ay, ax) - body)


@_F
def _to_velocity(wx, wy, bvx, bvy, rate, body, prm):
    """skills.accelerate_ball_to_velocity."""
    ax, ay = wx - bvx, wy - bvy
    kind, power, angle = _kick_for(ax, ay, rate, body)
    if _hyp(ax, ay) < prm[B_ACC] and power <= prm[MAX_POWER]:
        return kind, power, angle
    heading = np.arctan2(wy, wx)
    across = -np.sin(heading) * bvx + np.cos(heading) * bvy
    full = max(rate * prm[MAX_POWER], 1e-6)
    ang = heading - np.arcsin(min(max(across / full, -1.0), 1.0))
    return KICK_KIND, prm[MAX_POWER], _wrap(ang - body)


@_F
def _freeze(px, py, vx, vy, body, bx, by, bvx, bvy, rate, prm):
    """skills.freeze_ball."""
    nx, ny = px + vx, py + vy
    power = min(_hyp(bvx, bvy) / max(rate, 1e-6), prm[MAX_POWER])
    against = np.arctan2(bvy, bvx) + PI
    sx = bx + bvx + power * rate * np.cos(against)
    sy = by + bvy + power * rate * np.sin(against)
    if _hyp(sx - nx, sy - ny) < FREEZE_STAYS * prm[KD]:
        return KICK_KIND, power, _wrap(against - body)
    ox, oy = bx - nx, by - ny
    reach = min(_hyp(ox, oy) - FREEZE_PULL_GAP, FREEZE_PULL_REACH * prm[KD])
    d = np.arctan2(oy, ox)
    ix, iy = nx + reach * np.cos(d), ny + reach * np.sin(d)
    return _to_velocity(ix - bx, iy - by, bvx, bvy, rate, body, prm)


@_F
def _close_to_body(px, py, vx, vy, body, bx, by, bvx, bvy, angle, ratio, prm):
    """skills.kick_ball_close_to_body."""
    reach = prm[P_SIZE] + prm[B_SIZE] + ratio * prm[MARGIN]
    sx = px + vx + reach * np.cos(angle)
    sy = py + vy + reach * np.sin(angle)
    rate = _kick_rate(px, py, body, bx, by, prm)
    kind, power, ang = _kick_for(sx - bx - bvx, sy - by - bvy, rate, body)
    if power > prm[MAX_POWER] and _hyp(bvx, bvy) > FREEZE_MIN_SPEED:
        return _freeze(px, py, vx, vy, body, bx, by, bvx, bvy, rate, prm)
    return kind, min(power, prm[MAX_POWER]), ang


@_F
def _hold(me, vpos, vvel, vbody, first_opp, count_opp, ratio, goal_x, prm, ip):
    """skills.hold_ball for player ``me`` (object index) against the opponents
    ``first_opp .. first_opp + count_opp - 1`` of its view."""
    px, py = vpos[me, 0], vpos[me, 1]
    vx, vy = vvel[me, 0], vvel[me, 1]
    body = vbody[me]
    bx, by = vpos[0, 0], vpos[0, 1]
    bvx, bvy = vvel[0, 0], vvel[0, 1]
    reach = prm[P_SIZE] + prm[B_SIZE] + ratio * prm[MARGIN]
    best, nearest = np.inf, first_opp
    if ip[REFERENCE_HOLD] != 0:
        for o in range(first_opp, first_opp + count_opp):
            d = _hyp(vpos[o, 0] - bx, vpos[o, 1] - by)
            if d < best:
                best, nearest = d, o
        relative = 0.0
        if best < HOLD_OPPONENT_RANGE:
            away = np.arctan2(py - vpos[nearest, 1], px - vpos[nearest, 0])
            side = -1.0 if _wrap(vbody[nearest] - away) > 0 else 1.0
            relative = _wrap(away + side * HOLD_SIDE_ANGLE - body)
        angle = _wrap(body + relative)
        tx, ty = px + ratio * np.cos(relative), py + ratio * np.sin(relative)
    else:
        for o in range(first_opp, first_opp + count_opp):
            d = _hyp(vpos[o, 0] - px, vpos[o, 1] - py)
            if d < best:
                best, nearest = d, o
        angle = body
        if best < HOLD_OPPONENT_RANGE:
            away = np.arctan2(py - vpos[nearest, 1], px - vpos[nearest, 0])
            plus = _wrap(away + HOLD_SIDE_ANGLE)
            minus = _wrap(away - HOLD_SIDE_ANGLE)
            dp = _hyp(px + reach * np.cos(plus) - bx, py + reach * np.sin(plus) - by)
            dm = _hyp(px + reach * np.cos(minus) - bx, py + reach * np.sin(minus) - by)
            angle = plus if dp <= dm else minus
        tx, ty = px + reach * np.cos(angle), py + reach * np.sin(angle)
    stays = _hyp(bx + bvx - (px + vx), by + bvy - (py + vy)) < HOLD_STAYS * prm[KD]
    if _hyp(bx - tx, by - ty) < HOLD_SPOT_TOLERANCE and stays:
        return _face(px, py, vx, vy, body, goal_x, 0.0, prm)
    return _close_to_body(px, py, vx, vy, body, bx, by, bvx, bvy, angle, ratio, prm)


@_F
def _pass(me, vpos, vvel, vbody, target, prm, ip):
    """skills.pass_ball of player ``me`` to object ``target`` of its view."""
    n, m = ip[N], ip[M]
    px, py = vpos[me, 0], vpos[me, 1]
    vx, vy = vvel[me, 0], vvel[me, 1]
    body = vbody[me]
    bx, by = vpos[0, 0], vpos[0, 1]
    bvx, bvy = vvel[0, 0], vvel[0, 1]
    opp_near = False
    for o in range(1 + n, 1 + n + m):
        if _hyp(vpos[o, 0] - bx, vpos[o, 1] - by) < PASS_OPPONENT_RANGE:
            opp_near = True
    trx, try_ = vpos[target, 0] - bx, vpos[target, 1] - by
    heading = np.arctan2(try_, trx)
    ratio = 1.0 / prm[B_DECAY]
    cycles = np.log1p(max(_hyp(trx, try_), 0.0) * (ratio - 1.0) / PASS_END_SPEED) / np.log(ratio)
    cycles = max(np.ceil(cycles - 1e-6), 0.0)
    speed = PASS_END_SPEED * ratio**cycles
    touch = prm[B_SIZE] + prm[P_SIZE]
    ax, ay = np.cos(heading), np.sin(heading)
    if _hyp(px + vx - (bx + speed * ax), py + vy - (by + speed * ay)) < touch:
        proj = (px - bx) * ax + (py - by) * ay
        speed = proj - touch if speed < proj else proj + touch
    wx, wy = speed * ax, speed * ay
    rate = _kick_rate(px, py, body, bx, by, prm)
    full = rate * prm[MAX_POWER]
    if speed > prm[B_SPEED]:
        across = -np.sin(heading) * bvx + np.cos(heading) * bvy
        ang = heading - np.arcsin(min(max(across / max(full, 1e-6), -1.0), 1.0))
        ok = _hyp(bvx + full * np.cos(ang), bvy + full * np.sin(ang)) > WHEN_TO_KICK * prm[B_ACC]
    else:
        needed = _hyp(wx - bvx, wy - bvy) / max(rate, 1e-6)
        ok = needed <= PASS_POWER_RATIO * prm[MAX_POWER] or (
            opp_near and needed <= PASS_POWER_RATIO_PRESSED * prm[MAX_POWER]
        )
    if ok:
        return _to_velocity(wx, wy, bvx, bvy, rate, body, prm)
    return _close_to_body(px, py, vx, vy, body, bx, by, bvx, bvy, body, REPOSITION_RATIO, prm)


@_FI
def _intercept(o, vpos, vvel, vbody, prm, ip, tabs, below):
    """skills.intercept_estimate for object ``o`` of a view: (cycles, x, y). With ``below`` at most the
    horizon, an interception in ``below`` cycles or more is not searched for: (below, 0, 0);
    NO_CAP searches to the horizon."""
    h = ip[HORIZON]
    kd, decay = prm[KD], prm[P_DECAY]
    px, py = vpos[o, 0], vpos[o, 1]
    pvx, pvy = vvel[o, 0], vvel[o, 1]
    bx, by = vpos[0, 0], vpos[0, 1]
    vx, vy = vvel[0, 0], vvel[0, 1]
    hx, hy = np.cos(vbody[o]), np.sin(vbody[o])
    speed = _hyp(pvx, pvy)
    c0 = COS_WHEN_TO_TURN
    c1, c2, turns_known = 0.0, 0.0, False  # the one- and two-turn cones, computed when first needed
    vsq = vx * vx + vy * vy
    dx, dy = bx - px, by - py
    ex, ey = dx - pvx, dy - pvy
    need_lin = 2.0 * (dx * vx + dy * vy)
    need_const = dx * dx + dy * dy
    err_lin = 2.0 * (ex * vx + ey * vy)
    err_const = ex * ex + ey * ey + 1e-12
    head_lin = vx * hx + vy * hy
    head_const = ex * hx + ey * hy
    forward = max(pvx * hx + pvy * hy, 0.0)
    first_gap = min(forward + prm[DASH_ACC], prm[P_SPEED]) - prm[CRUISE]
    for i in range(min(h + 1, below)):
        t = tabs[T_TRAVEL, i]
        moved = t * t * vsq
        need = np.sqrt(max(t * need_lin + need_const + moved, 0.0)) - kd
        straight = tabs[T_SERIES, i] * first_gap + tabs[T_CRUISE, i]
        longest = max(straight, max(tabs[T_REACH + 1, i], max(tabs[T_REACH + 2, i], tabs[T_REACH + 3, i])))
        if need > longest:  # out of reach however it turns: the heading need not be computed
            continue
        err = (t * head_lin + head_const) / np.sqrt(max(t * err_lin + err_const + moved, 1e-12))
        if err >= c0:
            reach = straight
        else:
            if not turns_known:
                cap = min(PI / (1.0 + prm[INERTIA] * speed), PI)
                c1 = np.cos(min(cap + WHEN_TO_TURN, PI))
                cap += min(PI / (1.0 + prm[INERTIA] * speed * decay), PI)
                c2 = np.cos(min(cap + WHEN_TO_TURN, PI))
                turns_known = True
            if err >= c1:
                reach = tabs[T_REACH + 1, i]
            elif err >= c2:
                reach = tabs[T_REACH + 2, i]
            else:
                reach = tabs[T_REACH + 3, i]
        if need <= reach:
            return i, bx + t * vx, by + t * vy
    if below <= h:
        return below, 0.0, 0.0
    still = 1.0 - prm[B_DECAY]
    rx, ry = bx + vx / still, by + vy / still
    return h + 1 + np.int64(np.ceil(_hyp(rx - px, ry - py) / prm[CRUISE])), rx, ry


@_FI
def _in_cone(ox, oy, ex, ey, qx, qy):
    sx, sy = ex - ox, ey - oy
    rx, ry = qx - ox, qy - oy
    seg_sq = sx * sx + sy * sy
    along = rx * sx + ry * sy
    rel_sq = rx * rx + ry * ry
    # ``&``, not ``and``: no branch to mispredict, and the grid loops vectorise
    return (
        (rel_sq * seg_sq < CONE_FACTOR * along * along)
        & (along >= 0.0)
        & (along <= seg_sq)
        & (rel_sq < seg_sq)
    )


@_FI
def _get_open_point(k, vpos, fx, fy, ip, opn):
    """skills.get_open_target for keeper ``k`` (0-based) of a view, passes from (fx, fy). The sums
    run player by player over all grid points at once (rows of ``opn``, the grid's x and y among
    them), which the compiler vectorises; each point's sum keeps the players' order. The blocked
    cones and the sums over all players stay for the next keeper of the same view while
    ``opn[O_HELD, 0]`` is set."""
    n, m = ip[N], ip[M]
    players = n + m
    points = opn.shape[1]
    total, mine, blocked, gx, gy = opn[O_TOTAL], opn[O_MINE], opn[O_BLOCKED], opn[O_GX], opn[O_GY]
    if opn[O_HELD, 0] == 0.0:
        for c in range(points):
            total[c] = 0.0
            blocked[c] = 0.0
        for t in range(1 + n, 1 + players):
            qx, qy = vpos[t, 0], vpos[t, 1]
            for c in range(points):
                if _in_cone(fx, fy, gx[c], gy[c], qx, qy):
                    blocked[c] = 1.0
        for q in range(1, 1 + players):
            qx, qy = vpos[q, 0], vpos[q, 1]
            for c in range(points):
                dx, dy = gx[c] - qx, gy[c] - qy
                total[c] += 1.0 / np.sqrt(dx * dx + dy * dy + 1e-12)
        opn[O_HELD, 0] = 1.0
    qx, qy = vpos[1 + k, 0], vpos[1 + k, 1]
    for c in range(points):
        dx, dy = gx[c] - qx, gy[c] - qy
        mine[c] = 1.0 / np.sqrt(dx * dx + dy * dy + 1e-12)
    best, bx, by = np.inf, 0.0, 0.0
    all_blocked = True
    for c in range(points):
        if blocked[c] == 0.0:
            all_blocked = False
        cong = total[c] - mine[c] + (BLOCKED_PENALTY if blocked[c] != 0.0 else 0.0)
        if cong < best:
            best, bx, by = cong, gx[c], gy[c]
    if all_blocked:
        return 0.0, 0.0
    return bx, by


@_F
def _block_point(vpos, with_ball, ip):
    """skills.block_pass_target: 4 m from the most open keeper towards the ball."""
    n, m = ip[N], ip[M]
    hx, hy = vpos[1 + with_ball, 0], vpos[1 + with_ball, 1]
    fewest, open_k = 1 << 62, 0
    for k in range(n):
        if k == with_ball:
            continue
        count = 0
        for t in range(1 + n, 1 + n + m):
            if _in_cone(hx, hy, vpos[1 + k, 0], vpos[1 + k, 1], vpos[t, 0], vpos[t, 1]):
                count += 1
        if count < fewest:
            fewest, open_k = count, k
    kx, ky = vpos[1 + open_k, 0], vpos[1 + open_k, 1]
    tx, ty = vpos[0, 0] - kx, vpos[0, 1] - ky
    step = min(_hyp(tx, ty), MARK_DISTANCE)
    d = np.arctan2(ty, tx)
    return kx + step * np.cos(d), ky + step * np.sin(d)
