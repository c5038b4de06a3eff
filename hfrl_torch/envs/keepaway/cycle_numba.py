"""Whole keepaway cycles in compiled code (numba), per field: decisions, the keepers' and takers'
skills, physics, referee, the players' world models, state variables, the benchmark keepers and
the SMDP advance to each field's next decision (``KeepawayConfig.kernels="cycle"``).

Each function below is the per-field twin of the torch path (simulator.py, skills.py, keepers.py,
takers.py, physics.py, referee.py, perception.py, state_vars.py, policies.py), in the same order of
operations but in float64 scalars: the state is stored as float32 after every cycle, so one cycle
agrees with the torch path within float32 rounding (not bit for bit: transcendental functions and
the intermediate precision differ; a branch taken on a near-tie can differ).

Randomness: :func:`cycle` reads the uniforms the torch path draws (``u`` [B, U], in its order), so a
single cycle can be compared with torch's; the multi-cycle kernels (:func:`advance_fields`,
:func:`advance_any`, :func:`play`) draw from one splitmix64 generator per field (``rng`` [B]), so
a field's play does not depend on the batch size, the thread count or the other fields.

The entry points split the fields into ``parts`` contiguous ranges, one per thread (numba's ``prange``
over the ranges; compiled_cycle.py picks ``parts``): OpenMP's workers take a range in microseconds, where a
Python thread pool's hand-off cost 75-150 us on this VM, which ate the gain of splitting one cycle.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from hfrl_torch.common.threads import part_range
from hfrl_torch.envs.keepaway.perception import COLLISION_BALL_GAP, SENSE_SPEED_QSTEP, STILL

PI = math.pi
TWO_PI = 2.0 * math.pi
DEG = math.pi / 180.0
WHEN_TO_TURN = math.radians(7.0)
COS_WHEN_TO_TURN = math.cos(min(WHEN_TO_TURN, math.pi))
MARK_TURN = math.radians(25.0)
HOLD_SIDE = math.radians(45.0)

TURN, DASH, KICK = 1, 2, 3

# float parameters (prm)
KD, B_DECAY, B_RAND, B_ACC, B_SPEED, B_SIZE = 0, 1, 2, 3, 4, 5
P_DECAY, P_RAND, P_SIZE, P_SPEED, P_ACC, MARGIN = 6, 7, 8, 9, 10, 11
DASH_RATE, KICK_RATE, MIN_DASH, MAX_POWER, KICK_RAND, INERTIA, MAX_MOMENT = 12, 13, 14, 15, 16, 17, 18
LENGTH, WIDTH, DASH_ACC, CRUISE = 19, 20, 21, 22
NUM_PRM = 23
# integer parameters (ip)
N, M, HORIZON, PASSES, TURNOVER, PERIOD = 0, 1, 2, 3, 4, 5
SERVER_PERCEPTION, NOISY_OBS, REFERENCE_HOLD, SERVER_TIMING, NOISE, POLAR = 6, 7, 8, 9, 10, 11
NUM_IP = 12
# per-cycle tables (tabs rows)
T_TRAVEL, T_SERIES, T_CRUISE, T_REACH = 0, 1, 2, 3  # T_REACH..T_REACH + 3: the reach table by turns

# scratch arrays (:func:`scratch`)
S_CMD, S_POS, S_VEL, S_BODY, S_ACC, S_HIT = 0, 1, 2, 3, 4, 5
S_ICYC, S_IPTS, S_TPTS, S_KPOS, S_TPOS, S_ORDER = 6, 7, 8, 9, 10, 11
NO_CAP = 1 << 62  # _intercept searches to its horizon
S_OPEN = 12
# rows of GetOpen's work array (``scr[S_OPEN]`` [6, grid points])
O_TOTAL, O_MINE, O_BLOCKED, O_GX, O_GY, O_HELD = 0, 1, 2, 3, 4, 5

GOAL_X = 52.5
SEE_CYCLES = 3

# The helpers skip numba's reference counting (``_nrt=False``; ``_FA`` for the few that allocate):
# a cycle's arrays are borrowed views and its work arrays come from :func:`scratch`, so counting
# them only cost time (a third of a cycle, measured with perf). ``error_model="numpy"``: a division
# by zero gives inf as in torch, and without the Python check the loops vectorise. ``_FI``: the hot
# skills inlined into their callers (a call passes every array field by value): 13 % faster play,
# twice the first compile (22 -> 42 s, once per numba cache).
_F = numba.njit(cache=True, _nrt=False, error_model="numpy")
_FA = numba.njit(cache=True, error_model="numpy")
_FI = numba.njit(cache=True, _nrt=False, error_model="numpy", inline="always")
_PAR = numba.njit(cache=True, nogil=True, parallel=True)  # the entry points: fields split over threads


@_F
def _wrap(a: float) -> float:
    x = a + PI
    return x - np.floor(x / TWO_PI) * TWO_PI - PI


@_F
def _hyp(x: float, y: float) -> float:
    return np.sqrt(x * x + y * y)


# ----------------------------------------------------------------------------- random numbers


@_F
def _next(rng: np.ndarray, b: int) -> float:
    """A uniform in [0, 1) with 24 random bits from field ``b``'s splitmix64 generator."""
    z = rng[b] + np.uint64(0x9E3779B97F4A7C15)
    rng[b] = z
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return np.float64(z >> np.uint64(40)) * (1.0 / 16777216.0)


@_F
def uniform_count(ip: np.ndarray) -> int:
    """Uniforms one field draws in a cycle: kick noise [P, 2], turn noise [P], movement noise
    [O, 2], withheld see information [P, O]."""
    players = ip[N] + ip[M]
    count = 0
    if ip[NOISE] != 0:
        count += 2 * players + players + 2 * (players + 1)
    if ip[SERVER_PERCEPTION] != 0:
        count += players * (players + 1)
    return count


# ------------------------------------------------------------------------- primitive commands


@_FI
def _face(px, py, vx, vy, body, tx, ty, prm):
    err = _wrap(np.arctan2(ty - (py + vy), tx - (px + vx)) - body)
    moment = err * (1.0 + prm[INERTIA] * _hyp(vx, vy))
    moment = min(max(moment, -prm[MAX_MOMENT]), prm[MAX_MOMENT])
    return TURN, 0.0, moment


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
    return DASH, _dash_power(px, py, vx, vy, body, tx, ty, prm), 0.0


@_FI
def _intercept_move(px, py, vx, vy, body, tx, ty, bx, by, prm):
    """skills.intercept_move."""
    kd = prm[KD]
    rx = tx - (px + vx / (1.0 - prm[P_DECAY]))
    ry = ty - (py + vy / (1.0 - prm[P_DECAY]))
    if _hyp(rx, ry) < 0.5:
        return _face(px, py, vx, vy, body, bx, by, prm)
    hx, hy = np.cos(body), np.sin(body)
    lateral = abs(hx * ry - hy * rx)
    far = _hyp(tx - px, ty - py)
    ratio = 3.0 if far > 20.0 else (2.0 if far > 10.0 else 0.9)
    err = _wrap(np.arctan2(ry, rx) - body)
    behind = _hyp(rx, ry) > 2.5 and abs(err) > 0.5 * PI
    if (lateral > ratio * kd or behind) and abs(err) > WHEN_TO_TURN:
        return _face(px, py, vx, vy, body, tx, ty, prm)
    return DASH, _dash_power(px, py, vx, vy, body, tx, ty, prm), 0.0


# ------------------------------------------------------------------------------------ kicking


@_FI
def _kick_rate(px, py, body, bx, by, prm):
    rx, ry = bx - px, by - py
    dir_diff = abs(_wrap(np.arctan2(ry, rx) - body))
    gap = _hyp(rx, ry) - prm[P_SIZE] - prm[B_SIZE]
    return prm[KICK_RATE] * (1.0 - 0.25 * dir_diff / PI - 0.25 * gap / prm[MARGIN])


@_F
def _kick_for(ax, ay, rate, body):
    return KICK, _hyp(ax, ay) / max(rate, 1e-6), _wrap(np.arctan2(ay, ax) - body)


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
    return KICK, prm[MAX_POWER], _wrap(ang - body)


@_F
def _freeze(px, py, vx, vy, body, bx, by, bvx, bvy, rate, prm):
    """skills.freeze_ball."""
    nx, ny = px + vx, py + vy
    power = min(_hyp(bvx, bvy) / max(rate, 1e-6), prm[MAX_POWER])
    against = np.arctan2(bvy, bvx) + PI
    sx = bx + bvx + power * rate * np.cos(against)
    sy = by + bvy + power * rate * np.sin(against)
    if _hyp(sx - nx, sy - ny) < 0.8 * prm[KD]:
        return KICK, power, _wrap(against - body)
    ox, oy = bx - nx, by - ny
    reach = min(_hyp(ox, oy) - 0.1, 0.7 * prm[KD])
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
    if power > prm[MAX_POWER] and _hyp(bvx, bvy) > 0.1:
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
        if best < 5.0:
            away = np.arctan2(py - vpos[nearest, 1], px - vpos[nearest, 0])
            side = -1.0 if _wrap(vbody[nearest] - away) > 0 else 1.0
            relative = _wrap(away + side * HOLD_SIDE - body)
        angle = _wrap(body + relative)
        tx, ty = px + ratio * np.cos(relative), py + ratio * np.sin(relative)
    else:
        for o in range(first_opp, first_opp + count_opp):
            d = _hyp(vpos[o, 0] - px, vpos[o, 1] - py)
            if d < best:
                best, nearest = d, o
        angle = body
        if best < 5.0:
            away = np.arctan2(py - vpos[nearest, 1], px - vpos[nearest, 0])
            plus = _wrap(away + HOLD_SIDE)
            minus = _wrap(away - HOLD_SIDE)
            dp = _hyp(px + reach * np.cos(plus) - bx, py + reach * np.sin(plus) - by)
            dm = _hyp(px + reach * np.cos(minus) - bx, py + reach * np.sin(minus) - by)
            angle = plus if dp <= dm else minus
        tx, ty = px + reach * np.cos(angle), py + reach * np.sin(angle)
    stays = _hyp(bx + bvx - (px + vx), by + bvy - (py + vy)) < 0.85 * prm[KD]
    if _hyp(bx - tx, by - ty) < 0.3 and stays:
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
        if _hyp(vpos[o, 0] - bx, vpos[o, 1] - by) < 2.0:
            opp_near = True
    trx, try_ = vpos[target, 0] - bx, vpos[target, 1] - by
    heading = np.arctan2(try_, trx)
    ratio = 1.0 / prm[B_DECAY]
    cycles = np.log1p(max(_hyp(trx, try_), 0.0) * (ratio - 1.0) / 1.2) / np.log(ratio)
    cycles = max(np.ceil(cycles - 1e-6), 0.0)
    speed = 1.2 * ratio**cycles
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
        ok = _hyp(bvx + full * np.cos(ang), bvy + full * np.sin(ang)) > 0.85 * prm[B_ACC]
    else:
        needed = _hyp(wx - bvx, wy - bvy) / max(rate, 1e-6)
        ok = needed <= 1.05 * prm[MAX_POWER] or (opp_near and needed <= 1.30 * prm[MAX_POWER])
    if ok:
        return _to_velocity(wx, wy, bvx, bvy, rate, body, prm)
    return _close_to_body(px, py, vx, vy, body, bx, by, bvx, bvy, body, 0.16, prm)


# ---------------------------------------------------------------------------- interception


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
def _keeper_intercepts(vpos, vvel, vbody, holder, kickable, prm, ip, tabs, icyc, ipts):
    """The keepers' interceptions in a view [n], as far as :func:`_fastest` and the commands read
    them: with the ball kickable only the holder's (it is the fastest; the others read its
    cycles); else each keeper's searched only below the fastest before it, since a later keeper
    counts only if strictly faster. The fastest's cycles and point are exact either way."""
    best = NO_CAP
    for k in range(ip[N]):
        if kickable and k != holder:
            icyc[k] = NO_CAP
            continue
        icyc[k], ipts[k, 0], ipts[k, 1] = _intercept(1 + k, vpos, vvel, vbody, prm, ip, tabs, best)
        best = min(best, icyc[k])


@_FI
def _fastest(icyc, holder, kickable):
    """keepers.fastest_keeper over the keepers' interception cycles ``icyc`` [n]."""
    best, fastest = 1 << 62, 0
    for k in range(icyc.shape[0]):
        c = -1 if (kickable and k == holder) else icyc[k]
        if c < best:
            best, fastest = c, k
    return fastest


# ---------------------------------------------------------------------- GetOpen and BlockPass


@_FI
def _in_cone(ox, oy, ex, ey, qx, qy):
    sx, sy = ex - ox, ey - oy
    rx, ry = qx - ox, qy - oy
    seg_sq = sx * sx + sy * sy
    along = rx * sx + ry * sy
    rel_sq = rx * rx + ry * ry
    # ``&``, not ``and``: no branch to mispredict, and the grid loops vectorise
    return (
        (rel_sq * seg_sq < (1.0 + 0.09) * along * along)
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
        cong = total[c] - mine[c] + (1e9 if blocked[c] != 0.0 else 0.0)
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
    step = min(_hyp(tx, ty), 4.0)
    d = np.arctan2(ty, tx)
    return kx + step * np.cos(d), ky + step * np.sin(d)


# --------------------------------------------------------------------- keepers' and takers' play


@_FI
def _keeper_command(k, vpos, vvel, vbody, icyc, ipts, holder, kickable, pass_target, prm, ip, tabs, opn):
    """keepers.keeper_commands for keeper ``k`` (0-based) acting on a view; ``icyc``/``ipts`` are
    the keepers' interceptions in that view."""
    n = ip[N]
    me = 1 + k
    px, py = vpos[me, 0], vpos[me, 1]
    vx, vy = vvel[me, 0], vvel[me, 1]
    body = vbody[me]
    bx, by = vpos[0, 0], vpos[0, 1]
    if kickable and k == holder:
        if pass_target >= 0:
            return _pass(me, vpos, vvel, vbody, 1 + pass_target, prm, ip)
        return _hold(me, vpos, vvel, vbody, 1 + n, ip[M], 0.7, GOAL_X, prm, ip)
    fastest = _fastest(icyc, holder, kickable)
    if k == fastest:
        return _intercept_move(px, py, vx, vy, body, ipts[k, 0], ipts[k, 1], bx, by, prm)
    h = ip[HORIZON]
    fc = max(icyc[fastest], 0)
    bvx, bvy = vvel[0, 0], vvel[0, 1]
    if fc <= h:
        fx, fy = bx + tabs[T_TRAVEL, fc] * bvx, by + tabs[T_TRAVEL, fc] * bvy
    else:
        fx, fy = bx + bvx / (1.0 - prm[B_DECAY]), by + bvy / (1.0 - prm[B_DECAY])
    tx, ty = _get_open_point(k, vpos, fx, fy, ip, opn)
    if _hyp(px - tx, py - ty) < 1.5:
        return _face(px, py, vx, vy, body, bx, by, prm)
    return _move_to(px, py, vx, vy, body, tx, ty, WHEN_TO_TURN, prm)


@_FI
def _taker_command(j, vpos, vvel, vbody, tcyc_pts, with_ball, prm, ip):
    """takers.taker_commands for taker ``j`` (0-based) acting on a view; ``tcyc_pts`` [m, 2] are
    the takers' interception points in it."""
    n, m = ip[N], ip[M]
    kd = prm[KD]
    me = 1 + n + j
    px, py = vpos[me, 0], vpos[me, 1]
    vx, vy = vvel[me, 0], vvel[me, 1]
    body = vbody[me]
    bx, by = vpos[0, 0], vpos[0, 1]
    mine = _hyp(px - bx, py - by)
    rank = 0
    nearest = np.inf
    for i in range(m):
        d = _hyp(vpos[1 + n + i, 0] - bx, vpos[1 + n + i, 1] - by)
        if d < mine or (d == mine and i < j):
            rank += 1
        nearest = min(nearest, d)
    if nearest <= kd and rank == 0:
        return _hold(me, vpos, vvel, vbody, 1, n, 0.3, -GOAL_X, prm, ip)
    if m > 2 and rank >= 2:
        tx, ty = _block_point(vpos, with_ball, ip)
        if _hyp(px - tx, py - ty) < 2.0:
            return _face(px, py, vx, vy, body, bx, by, prm)
        return _move_to(px, py, vx, vy, body, tx, ty, MARK_TURN, prm)
    keeper_near = np.inf
    for k in range(n):
        keeper_near = min(keeper_near, _hyp(vpos[1 + k, 0] - bx, vpos[1 + k, 1] - by))
    if nearest < keeper_near and nearest <= kd and rank != 0:
        return _face(px, py, vx, vy, body, bx, by, prm)
    return _intercept_move(px, py, vx, vy, body, tcyc_pts[j, 0], tcyc_pts[j, 1], bx, by, prm)


@_F
def _commands(b, pos, vel, body, spos, svel, sbody, holder, kickable, pass_target, prm, ip, tabs, scr):
    """Every player's command [P, 3] (kind, power, angle) of field ``b`` into ``scr``'s first array."""
    n, m = ip[N], ip[M]
    cmd, icyc, ipts, tpts, opn = scr[S_CMD], scr[S_ICYC], scr[S_IPTS], scr[S_TPTS], scr[S_OPEN]
    opn[O_HELD, 0] = 0.0
    if ip[SERVER_PERCEPTION] == 0:
        vpos, vvel, vbody = pos[b], vel[b], body[b]
        _keeper_intercepts(vpos, vvel, vbody, holder, kickable, prm, ip, tabs, icyc, ipts)
        for j in range(m):
            _, tpts[j, 0], tpts[j, 1] = _intercept(1 + n + j, vpos, vvel, vbody, prm, ip, tabs, NO_CAP)
        with_ball = _fastest(icyc, holder, kickable)
        for k in range(n):
            kind, power, angle = _keeper_command(
                k, vpos, vvel, vbody, icyc, ipts, holder, kickable, pass_target, prm, ip, tabs, opn
            )
            cmd[k, 0], cmd[k, 1], cmd[k, 2] = kind, power, angle
        for j in range(m):
            kind, power, angle = _taker_command(j, vpos, vvel, vbody, tpts, with_ball, prm, ip)
            cmd[n + j, 0], cmd[n + j, 1], cmd[n + j, 2] = kind, power, angle
        return
    for k in range(n):
        vpos, vvel, vbody = spos[b, k], svel[b, k], sbody[b, k]
        opn[O_HELD, 0] = 0.0
        if not (kickable and k == holder):  # the holder passes or holds: it reads no interception
            _keeper_intercepts(vpos, vvel, vbody, holder, kickable, prm, ip, tabs, icyc, ipts)
        kind, power, angle = _keeper_command(
            k, vpos, vvel, vbody, icyc, ipts, holder, kickable, pass_target, prm, ip, tabs, opn
        )
        cmd[k, 0], cmd[k, 1], cmd[k, 2] = kind, power, angle
    for j in range(m):
        vpos, vvel, vbody = spos[b, n + j], svel[b, n + j], sbody[b, n + j]
        _, tpts[j, 0], tpts[j, 1] = _intercept(1 + n + j, vpos, vvel, vbody, prm, ip, tabs, NO_CAP)  # its own
        with_ball = holder
        if m > 2:
            _keeper_intercepts(vpos, vvel, vbody, holder, kickable, prm, ip, tabs, icyc, ipts)
            with_ball = _fastest(icyc, holder, kickable)
        kind, power, angle = _taker_command(j, vpos, vvel, vbody, tpts, with_ball, prm, ip)
        cmd[n + j, 0], cmd[n + j, 1], cmd[n + j, 2] = kind, power, angle


# ------------------------------------------------------------------------------ world models


@_F
def _qdist_of(tenths):
    """The quantised distance whose log rounds to ``tenths`` tenths."""
    return np.rint(np.exp(tenths * 0.1) / 0.1) * 0.1


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


QDIST_LOW, QDIST_HIGH = -240, 60  # log(1e-10) is -230 tenths; the field's diagonal is under 400 m
QDIST, COS_DEG, SIN_DEG = _quantisation_tables()


@_F
def _qdist(d):
    tenths = np.rint(np.log(d + 1e-10) / 0.1)
    if QDIST_LOW <= tenths <= QDIST_HIGH:
        return QDIST[np.int64(tenths) - QDIST_LOW]
    return _qdist_of(tenths)


@_F
def _qdir(a):
    return np.rint(a / DEG) * DEG


@_F
def _observe(b, p, pos, vel, body, spos, svel, sbody, u, u0, use_u, prm, ip):
    """perception.observe for observer ``p`` (0-based player) of field ``b``: its belief (holding
    the prior, already extrapolated) replaced by a see of the true state; ``u[u0 + o]`` are the
    withheld-information uniforms."""
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
            far = min(max((qdist - 20.0) / 20.0, 0.0), 1.0)
            withheld = u[u0 + o] < far and seen
        if withheld:
            continue
        wx, wy = vel[b, o, 0] - mvx, vel[b, o, 1] - mvy
        ex, ey = rx / safe, ry / safe
        dist_chg = wx * ex + wy * ey
        dir_chg = ((wy * ex - wx * ey) / safe) / DEG
        if dir_chg != 0:
            dir_chg = np.rint(dir_chg / 0.1) * 0.1
        qdist_chg = qdist * np.rint((dist_chg / safe) / 0.02) * 0.02
        turn = dir_chg * DEG * qdist
        ca, sa = COS_DEG[np.int64(deg) + 180], SIN_DEG[np.int64(deg) + 180]
        rvx = qdist_chg * ca - turn * sa
        rvy = qdist_chg * sa + turn * ca
        svel[b, p, o, 0] = mvx + (ch * rvx - sh * rvy)
        svel[b, p, o, 1] = mvy + (sh * rvx + ch * rvy)
        sbody[b, p, o] = _wrap(head + _qdir(_wrap(body[b, o] - head)))
    # the ball (calculateStateBall)
    nvx, nvy = svel[b, p, 0, 0], svel[b, p, 0, 1]
    bound = 2.0 * prm[B_RAND] * _hyp(prior_bvx, prior_bvy)
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
def _own_truth(b, p, pos, vel, body, spos, svel, sbody):
    me = 1 + p
    spos[b, p, me, 0], spos[b, p, me, 1] = pos[b, me, 0], pos[b, me, 1]
    svel[b, p, me, 0], svel[b, p, me, 1] = vel[b, me, 0], vel[b, me, 1]
    sbody[b, p, me] = body[b, me]


@_F
def _extrapolate(b, p, kax, kay, kicked, spos, svel, prm, ip):
    """perception.extrapolate for observer ``p``: its belief one cycle on, in place; (kax, kay)
    is the acceleration its own kick should give the believed ball."""
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
    drift = (0.5 if nvx > 1.0 else 0.25) if nvx > 0 else (-0.5 if nvx < -1.0 else -0.25)
    for o in range(opps, opps + count_opps):
        if o == fastest:
            d = np.arctan2(nby - spos[b, p, o, 1], nbx - spos[b, p, o, 0])
            spos[b, p, o, 0] = spos[b, p, o, 0] + 0.3 * np.cos(d)
            spos[b, p, o, 1] = spos[b, p, o, 1] + 0.3 * np.sin(d)
        else:
            spos[b, p, o, 0] = spos[b, p, o, 0] + drift
        svel[b, p, o, 0] = svel[b, p, o, 0] * prm[P_DECAY]
        svel[b, p, o, 1] = svel[b, p, o, 1] * prm[P_DECAY]


@_F
def _nearest_other(b, p, pos, spos, players, prm):
    """The distance from observer ``p`` to the nearest other player in its belief (1000 if none, as
    ``getClosestInSetTo``), or -1 when its believed ball is too far for a collision this cycle: the
    ball must end within 1.585 m, it moves less than 2 B_SPEED in a cycle (a seen velocity is capped
    near B_SPEED) and the player at most P_SPEED."""
    o = 1 + p
    reach = prm[KD] + 0.5 + 2.0 * prm[B_SPEED] + prm[P_SPEED]
    if _hyp(spos[b, p, 0, 0] - pos[b, o, 0], spos[b, p, 0, 1] - pos[b, o, 1]) >= reach:
        return -1.0
    nearest = 1000.0
    for q in range(players):
        if q != p:
            nearest = min(
                nearest, _hyp(spos[b, p, 1 + q, 0] - pos[b, o, 0], spos[b, p, 1 + q, 1] - pos[b, o, 1])
            )
    return nearest


@_F
def _after_collision(b, p, pos, vel, body, cmd, new_vel, new_body, nearest, spos, svel, prm):
    """perception.after_collision for observer ``p``, in place: ``pos``, ``vel``, ``body`` still hold
    the state before the cycle, ``new_vel`` [O, 2] and ``new_body`` [O] the one after it (reported as
    sense_body does); ``nearest`` is :func:`_nearest_other` (-1: no collision possible)."""
    if nearest < 0.0:
        return
    o = 1 + p
    kind = np.int64(cmd[p, 0])
    px, py, vx, vy = pos[b, o, 0], pos[b, o, 1], vel[b, o, 0], vel[b, o, 1]
    if kind in (DASH, TURN):
        if kind == DASH:
            pw = min(max(cmd[p, 1], prm[MIN_DASH]), prm[MAX_POWER]) * prm[DASH_RATE]
            vx, vy = vx + pw * np.cos(body[b, o]), vy + pw * np.sin(body[b, o])
        scale = min(prm[P_SPEED] / max(_hyp(vx, vy), 1e-12), 1.0)
        vx, vy = vx * scale, vy * scale
        px, py = px + vx, py + vy
        vx, vy = vx * prm[P_DECAY], vy * prm[P_DECAY]
    bx, by = spos[b, p, 0, 0], spos[b, p, 0, 1]
    d_ball = _hyp(bx - px, by - py)
    if d_ball >= prm[KD] + 0.5 or d_ball >= nearest:  # no test can pass, or another player is blamed
        return
    nb = new_body[o]
    sensed = np.rint(_hyp(new_vel[o, 0], new_vel[o, 1]) / SENSE_SPEED_QSTEP) * SENSE_SPEED_QSTEP
    heading = nb + _qdir(_wrap(np.arctan2(new_vel[o, 1], new_vel[o, 0]) - nb))
    sx, sy = sensed * np.cos(heading), sensed * np.sin(heading)
    predicted = _hyp(vx, vy)
    still = sensed < STILL
    turned = ((vx > 0) != (sx > 0) or abs(vx) < 0.08) and ((vy > 0) != (sy > 0) or abs(vy) < 0.08)
    collided = (
        (still and predicted > 0.01 and d_ball < 0.8)
        or (still and d_ball < prm[P_SIZE] + prm[B_SIZE])
        or (d_ball < prm[KD] + 0.5 and not still and turned and sensed < 0.25 * predicted)
    )
    if collided and d_ball < nearest:
        a = np.arctan2(by - py, bx - px)
        spos[b, p, 0, 0] = px + COLLISION_BALL_GAP * np.cos(a)
        spos[b, p, 0, 1] = py + COLLISION_BALL_GAP * np.sin(a)
        svel[b, p, 0, 0] = -0.1 * svel[b, p, 0, 0]
        svel[b, p, 0, 1] = -0.1 * svel[b, p, 0, 1]


@_F
def _sees(clock, phase):
    return (clock + phase) % SEE_CYCLES != SEE_CYCLES - 1


# --------------------------------------------------------------------------------- decisions


@_F
def _decision(b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip):
    """KeepawaySimulator.decision for field ``b``: (holder, kickable, must_decide)."""
    n = ip[N]
    bx, by = pos[b, 0, 0], pos[b, 0, 1]
    best, holder = np.inf, 0
    for k in range(n):
        d = _hyp(pos[b, 1 + k, 0] - bx, pos[b, 1 + k, 1] - by)
        if d < best:
            best, holder = d, k
    kickable = best <= prm[KD]
    passing = pass_target[b] >= 0
    if ip[SERVER_TIMING] != 0:
        if ip[SERVER_PERCEPTION] != 0:
            kickable = (
                _hyp(
                    spos[b, holder, 0, 0] - pos[b, 1 + holder, 0],
                    spos[b, holder, 0, 1] - pos[b, 1 + holder, 1],
                )
                < prm[KD]
            )
        if _sees(clock[b], phase[b, holder]):
            passing = False
    holding = pass_target[b] < 0 and ep[b] - action_start[b] < ip[PERIOD]
    running = prev_holder[b] == holder and (passing or holding)
    return holder, kickable, kickable and not running


@_F
def _view(b, decider, pos, body, spos, ip, kpos, tpos):
    """KeepawaySimulator._seen_positions: keepers [n, 2] and takers [m, 2] as ``decider`` sees them."""
    n, m = ip[N], ip[M]
    for o in range(n + m):
        if ip[SERVER_PERCEPTION] != 0:
            x, y = spos[b, decider, 1 + o, 0], spos[b, decider, 1 + o, 1]
        else:
            x, y = pos[b, 1 + o, 0], pos[b, 1 + o, 1]
            if ip[NOISY_OBS] != 0 and o != decider:
                mx, my = pos[b, 1 + decider, 0], pos[b, 1 + decider, 1]
                mb = body[b, 1 + decider]
                rx, ry = x - mx, y - my
                dist = _hyp(rx, ry)
                if dist > 0:
                    qd = _qdist(dist)
                    qa = _qdir(_wrap(np.arctan2(ry, rx) - mb)) + mb
                    x, y = mx + qd * np.cos(qa), my + qd * np.sin(qa)
        if o < n:
            kpos[o, 0], kpos[o, 1] = x, y
        else:
            tpos[o - n, 0], tpos[o - n, 1] = x, y


@_F
def _order(kpos, decider, order):
    """state_vars.teammate_order: the decider's teammates [n - 1], nearest first (ties: lower index)."""
    n = kpos.shape[0]
    used = np.int64(1) << decider
    for r in range(n - 1):
        best, pick = np.inf, -1
        for k in range(n):
            if (used >> k) & 1:
                continue
            d = _hyp(kpos[k, 0] - kpos[decider, 0], kpos[k, 1] - kpos[decider, 1])
            if pick < 0 or d < best:
                best, pick = d, k
        used |= np.int64(1) << pick
        order[r] = pick


@_FA
def _state_vars(kpos, tpos, decider, order, obs):
    """state_vars.keeper_state_variables into ``obs`` [4n + 2m - 3]."""
    n, m = kpos.shape[0], tpos.shape[0]
    _order(kpos, decider, order)
    k1x, k1y = kpos[decider, 0], kpos[decider, 1]
    tdist = np.empty(m)
    for j in range(m):
        tdist[j] = _hyp(tpos[j, 0] - k1x, tpos[j, 1] - k1y)
    torder = np.empty(m, dtype=np.int64)
    used = np.zeros(m, dtype=np.bool_)
    for r in range(m):
        best, pick = np.inf, -1
        for j in range(m):
            if not used[j] and (pick < 0 or tdist[j] < best):
                best, pick = tdist[j], j
        used[pick] = True
        torder[r] = pick
    i = 0
    obs[i] = _hyp(k1x, k1y)
    i += 1
    for r in range(n - 1):
        obs[i] = _hyp(kpos[order[r], 0] - k1x, kpos[order[r], 1] - k1y)
        i += 1
    for r in range(m):
        obs[i] = tdist[torder[r]]
        i += 1
    for r in range(n - 1):
        obs[i] = _hyp(kpos[order[r], 0], kpos[order[r], 1])
        i += 1
    for r in range(m):
        obs[i] = _hyp(tpos[torder[r], 0], tpos[torder[r], 1])
        i += 1
    for r in range(n - 1):
        best = np.inf
        for j in range(m):
            best = min(best, _hyp(kpos[order[r], 0] - tpos[j, 0], kpos[order[r], 1] - tpos[j, 1]))
        obs[i] = best
        i += 1
    for r in range(n - 1):
        ax, ay = kpos[order[r], 0] - k1x, kpos[order[r], 1] - k1y
        best = np.inf
        for j in range(m):
            bx, by = tpos[j, 0] - k1x, tpos[j, 1] - k1y
            ang = np.arctan2(abs(ax * by - ay * bx), ax * bx + ay * by) / DEG
            best = min(best, ang)
        obs[i] = best
        i += 1


@_FA
def _observation(b, decider, pos, body, spos, ip, kpos, tpos, order, obs, obs_out):
    """Keeper ``decider``'s state variables on field ``b`` into ``obs_out[b]`` (``order`` keeps its
    teammate order)."""
    _view(b, decider, pos, body, spos, ip, kpos, tpos)
    _state_vars(kpos, tpos, decider, order, obs)
    for i in range(obs.shape[0]):
        obs_out[b, i] = obs[i]


@_F
def _policy_action(policy, obs, rng, b, ip):
    """The benchmark keepers (policies.py): 0 Always Hold, 1 Random, 2 Hand-coded."""
    n, m = ip[N], ip[M]
    if policy == 0:
        return 0
    if policy == 1:
        return min(np.int64(_next(rng, b) * n), n - 1)
    if obs[n] > 5.0:
        return 0
    start = 2 * n + 2 * m - 1
    best, action = np.float32(90.0), 0
    for k in range(n - 1):
        score = np.float32(np.float32(4.0) * np.float32(obs[start + k]) + np.float32(obs[start + n - 1 + k]))
        if score > best:
            best, action = score, k + 1
    return action


# ------------------------------------------------------------------------------------ a cycle


@_F
def _cycle(
    b,
    pos,
    vel,
    body,
    counter,
    ep,
    last_dec,
    prev_holder,
    pass_target,
    action_start,
    clock,
    phase,
    spos,
    svel,
    sbody,
    action,
    u,
    prm,
    ip,
    tabs,
    scr,
):
    """KeepawaySimulator.step for field ``b`` (active), the holder reading ``action`` if it must
    decide; ``u`` its uniforms in the torch path's order, ``scr`` the :func:`scratch` arrays.
    Returns the end cause (0 running)."""
    n, m = ip[N], ip[M]
    players = n + m
    objects = 1 + players
    holder, kickable, must = _decision(
        b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip
    )
    if must:
        target = -1
        if action > 0:
            kpos, tpos, order = scr[S_KPOS], scr[S_TPOS], scr[S_ORDER]
            _view(b, holder, pos, body, spos, ip, kpos, tpos)
            _order(kpos, holder, order)
            target = order[min(max(action, 1), n - 1) - 1]
        pass_target[b] = target
        action_start[b] = ep[b]
        last_dec[b, holder] = ep[b]
    if not kickable:
        pass_target[b] = -1
    _commands(b, pos, vel, body, spos, svel, sbody, holder, kickable, pass_target[b], prm, ip, tabs, scr)
    cmd = scr[S_CMD]

    # physics (the old positions stay in ``pos`` until the end: the world models need them)
    noise = ip[NOISE] != 0
    u_kick, u_turn, u_move = 0, 2 * players, 3 * players
    u_seen = 3 * players + 2 * objects if noise else 0
    bx, by = pos[b, 0, 0], pos[b, 0, 1]
    bvx, bvy = vel[b, 0, 0], vel[b, 0, 1]
    new_pos, new_vel, new_body, acc, hit = scr[S_POS], scr[S_VEL], scr[S_BODY], scr[S_ACC], scr[S_HIT]
    for o in range(objects):
        acc[o, 0], acc[o, 1] = 0.0, 0.0
        hit[o] = False
    new_body[0] = body[b, 0]
    for p in range(players):
        o = 1 + p
        kind, power, angle = np.int64(cmd[p, 0]), cmd[p, 1], cmd[p, 2]
        px, py, pb = pos[b, o, 0], pos[b, o, 1], body[b, o]
        if kind == KICK:
            rx, ry = bx - px, by - py
            dist = _hyp(rx, ry)
            if dist <= prm[KD]:
                pw = min(max(power, 0.0), prm[MAX_POWER])
                dir_diff = abs(_wrap(np.arctan2(ry, rx) - pb))
                gap = dist - prm[P_SIZE] - prm[B_SIZE]
                rate = prm[KICK_RATE] * (1.0 - 0.25 * dir_diff / PI - 0.25 * gap / prm[MARGIN])
                ax, ay = pw * rate * np.cos(pb + angle), pw * rate * np.sin(pb + angle)
                if noise and prm[KICK_RAND] > 0:
                    max_rand = (
                        prm[KICK_RAND]
                        * (pw / prm[MAX_POWER])
                        * (
                            (0.5 + 0.25 * (dir_diff / PI + gap / prm[MARGIN]))
                            + (0.5 + 0.5 * _hyp(bvx, bvy) / (prm[B_SPEED] * prm[B_DECAY]))
                        )
                    )
                    radius = u[u_kick + 2 * p] * max_rand
                    a = (2.0 * u[u_kick + 2 * p + 1] - 1.0) * PI
                    ax, ay = ax + radius * np.cos(a), ay + radius * np.sin(a)
                acc[0, 0] += ax
                acc[0, 1] += ay
        elif kind == DASH:
            pw = min(max(power, prm[MIN_DASH]), prm[MAX_POWER]) * prm[DASH_RATE]
            acc[o, 0], acc[o, 1] = pw * np.cos(pb), pw * np.sin(pb)
        new_body[o] = pb
        if kind == TURN:
            moment = min(max(angle, -prm[MAX_MOMENT]), prm[MAX_MOMENT])
            actual = moment / (1.0 + prm[INERTIA] * _hyp(vel[b, o, 0], vel[b, o, 1]))
            if noise:
                actual = actual * (1.0 + prm[P_RAND] * (2.0 * u[u_turn + p] - 1.0))
            new_body[o] = _wrap(pb + actual)
    for o in range(objects):
        ball = o == 0
        amax = prm[B_ACC] if ball else prm[P_ACC]
        vmax = prm[B_SPEED] if ball else prm[P_SPEED]
        ax, ay = acc[o, 0], acc[o, 1]
        scale = min(amax / max(_hyp(ax, ay), 1e-12), 1.0)
        vx, vy = vel[b, o, 0] + ax * scale, vel[b, o, 1] + ay * scale
        scale = min(vmax / max(_hyp(vx, vy), 1e-12), 1.0)
        vx, vy = vx * scale, vy * scale
        if noise:
            r = (prm[B_RAND] if ball else prm[P_RAND]) * _hyp(vx, vy)
            u1, u2 = u[u_move + 2 * o], u[u_move + 2 * o + 1]
            if ip[POLAR] != 0:
                a = (2.0 * u2 - 1.0) * PI
                vx, vy = vx + u1 * r * np.cos(a), vy + u1 * r * np.sin(a)
            else:
                vx, vy = vx + (2.0 * u1 - 1.0) * r, vy + (2.0 * u2 - 1.0) * r
        new_pos[o, 0], new_pos[o, 1] = pos[b, o, 0] + vx, pos[b, o, 1] + vy
        decay = prm[B_DECAY] if ball else prm[P_DECAY]
        new_vel[o, 0], new_vel[o, 1] = vx * decay, vy * decay
    # collisions (physics.resolve_collisions: pairs in order, at most ``PASSES`` passes)
    for _ in range(ip[PASSES]):
        overlap = False
        for i in range(objects):
            for j in range(i + 1, objects):
                contact = (prm[B_SIZE] if i == 0 else prm[P_SIZE]) + prm[P_SIZE]
                if _hyp(new_pos[j, 0] - new_pos[i, 0], new_pos[j, 1] - new_pos[i, 1]) < contact:
                    overlap = True
        if not overlap:
            break
        k = 0
        for i in range(objects):
            for j in range(i + 1, objects):
                contact = (prm[B_SIZE] if i == 0 else prm[P_SIZE]) + prm[P_SIZE]
                dx, dy = new_pos[j, 0] - new_pos[i, 0], new_pos[j, 1] - new_pos[i, 1]
                dist = _hyp(dx, dy)
                if dist < contact:
                    if dist > 1e-9:
                        ax, ay = dx / dist, dy / dist
                    else:
                        a = k * 2.399963229728653
                        ax, ay = np.cos(a), np.sin(a)
                    push = 0.5 * (contact - dist) + 1e-6
                    new_pos[i, 0] -= push * ax
                    new_pos[j, 0] += push * ax
                    new_pos[i, 1] -= push * ay
                    new_pos[j, 1] += push * ay
                    hit[i] = True
                    hit[j] = True
                k += 1
    for o in range(objects):
        if hit[o]:
            new_vel[o, 0] *= -0.1
            new_vel[o, 1] *= -0.1

    # referee
    kd = prm[KD]
    nbx, nby = new_pos[0, 0], new_pos[0, 1]
    keeper_near, taker_near = False, False
    for o in range(1, objects):
        if _hyp(new_pos[o, 0] - nbx, new_pos[o, 1] - nby) <= kd:
            if o <= n:
                keeper_near = True
            else:
                taker_near = True
    if taker_near:
        counter[b] += 1
    elif keeper_near:
        counter[b] = 0
    cause = 0
    if not (abs(nbx) < 0.5 * prm[LENGTH] and abs(nby) < 0.5 * prm[WIDTH]):
        cause = 1
    elif counter[b] >= ip[TURNOVER]:
        cause = 2

    # world models: extrapolate from the old belief and the own command, then see the new state
    server = ip[SERVER_PERCEPTION] != 0
    if server:
        for p in range(players):
            o = 1 + p
            kax, kay, kicked = 0.0, 0.0, False
            if np.int64(cmd[p, 0]) == KICK:
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
            nearest = _nearest_other(b, p, pos, spos, players, prm)  # before the extrapolation
            _extrapolate(b, p, kax, kay, kicked, spos, svel, prm, ip)
            _after_collision(b, p, pos, vel, body, cmd, new_vel, new_body, nearest, spos, svel, prm)
    for o in range(objects):
        pos[b, o, 0], pos[b, o, 1] = new_pos[o, 0], new_pos[o, 1]
        vel[b, o, 0], vel[b, o, 1] = new_vel[o, 0], new_vel[o, 1]
        body[b, o] = new_body[o]
    ep[b] += 1
    clock[b] += 1
    if server:
        for p in range(players):
            if _sees(clock[b], phase[b, p]):
                _observe(b, p, pos, vel, body, spos, svel, sbody, u, u_seen + p * objects, True, prm, ip)
            _own_truth(b, p, pos, vel, body, spos, svel, sbody)
    prev_holder[b] = holder if kickable else -1
    if ip[SERVER_TIMING] != 0:
        h2, k2, _ = _decision(b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip)
        if k2 and prev_holder[b] == h2 and pass_target[b] >= 0:
            last_dec[b, h2] = ep[b]
    return cause


@_FA
def _reset_field(
    b,
    pos,
    vel,
    body,
    counter,
    ep,
    last_dec,
    prev_holder,
    pass_target,
    action_start,
    spos,
    svel,
    sbody,
    rng,
    prm,
    ip,
):
    """KeepawaySimulator.fresh_state for field ``b``, drawn from its own generator."""
    n, m = ip[N], ip[M]
    hx, hy = 0.5 * prm[LENGTH], 0.5 * prm[WIDTH]
    k0 = min(np.int64(_next(rng, b) * n), n - 1)
    for i in range(n):
        u1, u2 = _next(rng, b), _next(rng, b)
        slot = (k0 + i) % n
        if slot < 3:
            sx = -1.0 if slot == 0 else 1.0
            sy = 1.0 if slot == 2 else -1.0
            pos[b, 1 + i, 0], pos[b, 1 + i, 1] = sx * (hx - 3.0 * u1), sy * (hy - 3.0 * u2)
        else:
            pos[b, 1 + i, 0], pos[b, 1 + i, 1] = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    for j in range(m):
        u1, u2 = _next(rng, b), _next(rng, b)
        pos[b, 1 + n + j, 0], pos[b, 1 + n + j, 1] = -(hx - 3.0 * u1), hy - 3.0 * u2
    pos[b, 0, 0], pos[b, 0, 1] = -hx + 4.0, -hy + 4.0
    for o in range(1 + n + m):
        vel[b, o, 0], vel[b, o, 1] = 0.0, 0.0
    counter[b] = 0
    ep[b] = 0
    for k in range(n):
        last_dec[b, k] = -1
    prev_holder[b] = -1
    pass_target[b] = -1
    action_start[b] = 0
    if ip[SERVER_PERCEPTION] != 0:
        for p in range(n + m):
            for o in range(1 + n + m):
                svel[b, p, o, 0], svel[b, p, o, 1] = 0.0, 0.0
            _observe(b, p, pos, vel, body, spos, svel, sbody, np.empty(1), 0, False, prm, ip)
            _own_truth(b, p, pos, vel, body, spos, svel, sbody)


@_FA
def view_work(ip, features):
    """The work arrays of a kernel that computes a holder's observation, made once per range: its view
    (keepers [n, 2], takers [m, 2]), its teammate order [n - 1] and its state variables [features]."""
    n, m = ip[N], ip[M]
    return np.empty((n, 2)), np.empty((m, 2)), np.empty(n - 1, dtype=np.int64), np.empty(features)


@_FA
def scratch(ip, grid):
    """One thread's work arrays for :func:`_cycle`, made once per range of a kernel call (indices ``S_*``):
    commands [P, 3], new positions, velocities and bodies, accelerations, collisions, the keepers'
    interception cycles and points, the takers' points, a holder's view and teammate order, and
    GetOpen's rows (``O_*``), its grid's x and y among them (contiguous: its loops vectorise, 5x
    faster than strided). Passed down whole only once per cycle: numba copies a tuple's every
    array into each call."""
    n, m = ip[N], ip[M]
    players = n + m
    objects = 1 + players
    opn = np.zeros((6, grid.shape[0]))
    opn[O_GX] = grid[:, 0]
    opn[O_GY] = grid[:, 1]
    return (
        np.empty((players, 3)),
        np.empty((objects, 2)),
        np.empty((objects, 2)),
        np.empty(objects),
        np.empty((objects, 2)),
        np.empty(objects, dtype=np.bool_),
        np.empty(n, dtype=np.int64),
        np.empty((n, 2)),
        np.empty((m, 2)),
        np.empty((n, 2)),
        np.empty((m, 2)),
        np.empty(max(n - 1, 1), dtype=np.int64),
        opn,
    )


@_F
def _fill(rng, b, u):
    for i in range(u.shape[0]):
        u[i] = _next(rng, b)


# ---------------------------------------------------------------------------- entry points


@_PAR
def cycle(
    pos: np.ndarray,
    vel: np.ndarray,
    body: np.ndarray,
    counter: np.ndarray,
    ep: np.ndarray,
    last_dec: np.ndarray,
    prev_holder: np.ndarray,
    pass_target: np.ndarray,
    action_start: np.ndarray,
    clock: np.ndarray,
    phase: np.ndarray,
    spos: np.ndarray,
    svel: np.ndarray,
    sbody: np.ndarray,
    actions: np.ndarray,
    active: np.ndarray,
    u: np.ndarray,
    prm: np.ndarray,
    ip: np.ndarray,
    tabs: np.ndarray,
    grid: np.ndarray,
    cause_out: np.ndarray,
    parts: int,
) -> None:
    """One cycle on the ``active`` fields, in place, with the torch path's uniforms ``u`` [B, U]; the
    fields split into ``parts`` ranges, one per thread (as in every entry point below)."""
    batch = pos.shape[0]
    for p in numba.prange(parts):
        scr = scratch(ip, grid)
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            cause_out[b] = 0
            if active[b]:
                cause_out[b] = _cycle(
                    b,
                    pos,
                    vel,
                    body,
                    counter,
                    ep,
                    last_dec,
                    prev_holder,
                    pass_target,
                    action_start,
                    clock,
                    phase,
                    spos,
                    svel,
                    sbody,
                    actions[b],
                    u[b],
                    prm,
                    ip,
                    tabs,
                    scr,
                )


@_PAR
def decisions(
    pos: np.ndarray,
    body: np.ndarray,
    clock: np.ndarray,
    phase: np.ndarray,
    spos: np.ndarray,
    pass_target: np.ndarray,
    prev_holder: np.ndarray,
    ep: np.ndarray,
    action_start: np.ndarray,
    prm: np.ndarray,
    ip: np.ndarray,
    holder_out: np.ndarray,
    kickable_out: np.ndarray,
    must_out: np.ndarray,
    obs_out: np.ndarray,
    parts: int,
) -> None:
    """The decision (holder, kickable, must decide) of every field and its holder's
    state variables."""
    batch = pos.shape[0]
    for p in numba.prange(parts):
        kpos, tpos, order, obs = view_work(ip, obs_out.shape[1])
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            h, k, must = _decision(
                b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip
            )
            holder_out[b], kickable_out[b], must_out[b] = h, k, must
            _observation(b, h, pos, body, spos, ip, kpos, tpos, order, obs, obs_out)


@_PAR
def observations(
    pos: np.ndarray,
    body: np.ndarray,
    spos: np.ndarray,
    decider: np.ndarray,
    ip: np.ndarray,
    obs_out: np.ndarray,
    order_out: np.ndarray,
    parts: int,
) -> None:
    """The state variables of keeper ``decider[b]`` on every field and its teammate order, as the
    compiled cycle numbers the teammates (its PassBall k goes to ``order_out[b, k - 1]``)."""
    batch = pos.shape[0]
    for p in numba.prange(parts):
        kpos, tpos, _, obs = view_work(ip, obs_out.shape[1])
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            _observation(b, decider[b], pos, body, spos, ip, kpos, tpos, order_out[b], obs, obs_out)


@_PAR
def advance_fields(
    pos: np.ndarray,
    vel: np.ndarray,
    body: np.ndarray,
    counter: np.ndarray,
    ep: np.ndarray,
    last_dec: np.ndarray,
    prev_holder: np.ndarray,
    pass_target: np.ndarray,
    action_start: np.ndarray,
    clock: np.ndarray,
    phase: np.ndarray,
    spos: np.ndarray,
    svel: np.ndarray,
    sbody: np.ndarray,
    rng: np.ndarray,
    actions: np.ndarray,
    first: np.ndarray,
    running: np.ndarray,
    restart: bool,
    max_cycles: int,
    prm: np.ndarray,
    ip: np.ndarray,
    tabs: np.ndarray,
    grid: np.ndarray,
    cycles_out: np.ndarray,
    cause_out: np.ndarray,
    parts: int,
) -> int:
    """Each ``running`` field on its own up to its holder's next decision: a first
    cycle with
    ``actions`` where ``first``, then cycles until the holder must decide or the episode ends
    (restarted and played on where ``restart``). ``cycles_out`` counts the cycles, ``cause_out``
    the end cause (0 where none). Returns the number of fields that hit ``max_cycles``."""
    batch = pos.shape[0]
    stuck = np.zeros(parts, dtype=np.int64)
    for p in numba.prange(parts):
        count = uniform_count(ip)
        scr = scratch(ip, grid)
        u = np.empty(count)
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            cycles_out[b] = 0
            cause_out[b] = 0
            if not running[b]:
                continue
            go = first[b]
            done = False
            for _ in range(max_cycles + 1):
                if not go:
                    _, _, must = _decision(
                        b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip
                    )
                    if must:
                        done = True
                        break
                _fill(rng, b, u)
                cause = _cycle(
                    b,
                    pos,
                    vel,
                    body,
                    counter,
                    ep,
                    last_dec,
                    prev_holder,
                    pass_target,
                    action_start,
                    clock,
                    phase,
                    spos,
                    svel,
                    sbody,
                    actions[b] if go else 0,
                    u,
                    prm,
                    ip,
                    tabs,
                    scr,
                )
                go = False
                cycles_out[b] += 1
                if cause != 0:
                    if restart:
                        _reset_field(
                            b,
                            pos,
                            vel,
                            body,
                            counter,
                            ep,
                            last_dec,
                            prev_holder,
                            pass_target,
                            action_start,
                            spos,
                            svel,
                            sbody,
                            rng,
                            prm,
                            ip,
                        )
                    else:
                        cause_out[b] = cause
                        done = True
                        break
            if not done:
                stuck[p] += 1
    return stuck.sum()


@_PAR
def _any_cycle(
    pos: np.ndarray,
    vel: np.ndarray,
    body: np.ndarray,
    counter: np.ndarray,
    ep: np.ndarray,
    last_dec: np.ndarray,
    prev_holder: np.ndarray,
    pass_target: np.ndarray,
    action_start: np.ndarray,
    clock: np.ndarray,
    phase: np.ndarray,
    spos: np.ndarray,
    svel: np.ndarray,
    sbody: np.ndarray,
    rng: np.ndarray,
    actions: np.ndarray,
    go: np.ndarray,
    running: np.ndarray,
    prm: np.ndarray,
    ip: np.ndarray,
    tabs: np.ndarray,
    grid: np.ndarray,
    cause_out: np.ndarray,
    must_out: np.ndarray,
    parts: int,
) -> None:
    """One ``sync="any"`` cycle of the ``running`` fields (``actions`` where ``go``): each one's end cause
    and, where it runs on, whether its holder must decide; the fields split into ``parts`` ranges, one
    per thread."""
    batch = pos.shape[0]
    for p in numba.prange(parts):
        count = uniform_count(ip)
        scr = scratch(ip, grid)
        u = np.empty(count)
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            must_out[b] = False
            if not running[b]:
                continue
            _fill(rng, b, u)
            cause = _cycle(
                b,
                pos,
                vel,
                body,
                counter,
                ep,
                last_dec,
                prev_holder,
                pass_target,
                action_start,
                clock,
                phase,
                spos,
                svel,
                sbody,
                actions[b] if go[b] else 0,
                u,
                prm,
                ip,
                tabs,
                scr,
            )
            cause_out[b] = cause
            if cause == 0:
                _, _, must = _decision(
                    b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip
                )
                must_out[b] = must


@numba.njit(cache=True)
def advance_any(
    pos: np.ndarray,
    vel: np.ndarray,
    body: np.ndarray,
    counter: np.ndarray,
    ep: np.ndarray,
    last_dec: np.ndarray,
    prev_holder: np.ndarray,
    pass_target: np.ndarray,
    action_start: np.ndarray,
    clock: np.ndarray,
    phase: np.ndarray,
    spos: np.ndarray,
    svel: np.ndarray,
    sbody: np.ndarray,
    rng: np.ndarray,
    actions: np.ndarray,
    first: np.ndarray,
    running: np.ndarray,
    max_cycles: int,
    prm: np.ndarray,
    ip: np.ndarray,
    tabs: np.ndarray,
    grid: np.ndarray,
    cycles_out: np.ndarray,
    cause_out: np.ndarray,
    parts: int,
) -> bool:
    """``sync="any"``: the ``running`` fields in lock-step (a first cycle with ``actions`` where
    ``first``) until one of them must decide or ends, each cycle split into ``parts`` field ranges.
    Returns False if ``max_cycles`` ran out."""
    batch = pos.shape[0]
    alive = running.copy()
    go = first.copy()
    step_cause = np.zeros(batch, dtype=np.int64)
    must = np.zeros(batch, dtype=np.bool_)
    for b in range(batch):
        cycles_out[b] = 0
        cause_out[b] = 0
    if not alive.any():
        return True
    check = not first.any()
    for b in range(batch):
        if alive[b]:
            _, _, must[b] = _decision(
                b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip
            )
    for _ in range(max_cycles + 1):
        if check:
            stop = False
            for b in range(batch):
                if alive[b] and must[b]:
                    stop = True
            if stop:
                return True
        _any_cycle(
            pos,
            vel,
            body,
            counter,
            ep,
            last_dec,
            prev_holder,
            pass_target,
            action_start,
            clock,
            phase,
            spos,
            svel,
            sbody,
            rng,
            actions,
            go,
            alive,
            prm,
            ip,
            tabs,
            grid,
            step_cause,
            must,
            parts,
        )
        ended = False
        for b in range(batch):
            if alive[b]:
                cycles_out[b] += 1
                if step_cause[b] != 0:
                    cause_out[b] = step_cause[b]
                    alive[b] = False
                    ended = True
            go[b] = False
        check = True
        if ended or not alive.any():
            return True
    return False


@_PAR
def play(
    pos: np.ndarray,
    vel: np.ndarray,
    body: np.ndarray,
    counter: np.ndarray,
    ep: np.ndarray,
    last_dec: np.ndarray,
    prev_holder: np.ndarray,
    pass_target: np.ndarray,
    action_start: np.ndarray,
    clock: np.ndarray,
    phase: np.ndarray,
    spos: np.ndarray,
    svel: np.ndarray,
    sbody: np.ndarray,
    rng: np.ndarray,
    policy: int,
    max_cycles: int,
    durations: np.ndarray,
    causes: np.ndarray,
    played: np.ndarray,
    prm: np.ndarray,
    ip: np.ndarray,
    tabs: np.ndarray,
    grid: np.ndarray,
    parts: int,
) -> int:
    """Benchmark keepers (``policy`` 0 hold, 1 random, 2 hand-coded) deciding inside each cycle, on
    every field until it has played ``durations.shape[1]`` episodes or
    ``max_cycles`` cycles; each
    ended episode's length and cause are stored, and the next one starts at once. Returns the
    field-cycles simulated."""
    batch = pos.shape[0]
    total = np.zeros(parts, dtype=np.int64)
    for p in numba.prange(parts):
        n, m = ip[N], ip[M]
        count = uniform_count(ip)
        quota = durations.shape[1]
        scr = scratch(ip, grid)
        u = np.empty(count)
        kpos, tpos, order, obs64 = view_work(ip, 4 * n + 2 * m - 3)
        obs = np.empty(4 * n + 2 * m - 3, dtype=np.float32)
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            for _ in range(max_cycles):
                if played[b] >= quota:
                    break
                action = 0
                if policy != 0:
                    h, _, must = _decision(
                        b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip
                    )
                    if must:
                        _view(b, h, pos, body, spos, ip, kpos, tpos)
                        _state_vars(kpos, tpos, h, order, obs64)
                        for i in range(obs.shape[0]):
                            obs[i] = obs64[i]
                        action = _policy_action(policy, obs, rng, b, ip)
                _fill(rng, b, u)
                cause = _cycle(
                    b,
                    pos,
                    vel,
                    body,
                    counter,
                    ep,
                    last_dec,
                    prev_holder,
                    pass_target,
                    action_start,
                    clock,
                    phase,
                    spos,
                    svel,
                    sbody,
                    action,
                    u,
                    prm,
                    ip,
                    tabs,
                    scr,
                )
                total[p] += 1
                if cause != 0:
                    durations[b, played[b]] = ep[b]
                    causes[b, played[b]] = cause
                    played[b] += 1
                    _reset_field(
                        b,
                        pos,
                        vel,
                        body,
                        counter,
                        ep,
                        last_dec,
                        prev_holder,
                        pass_target,
                        action_start,
                        spos,
                        svel,
                        sbody,
                        rng,
                        prm,
                        ip,
                    )
    return total.sum()


@_PAR
def reset_fields(
    pos: np.ndarray,
    vel: np.ndarray,
    body: np.ndarray,
    counter: np.ndarray,
    ep: np.ndarray,
    last_dec: np.ndarray,
    prev_holder: np.ndarray,
    pass_target: np.ndarray,
    action_start: np.ndarray,
    spos: np.ndarray,
    svel: np.ndarray,
    sbody: np.ndarray,
    rng: np.ndarray,
    mask: np.ndarray,
    prm: np.ndarray,
    ip: np.ndarray,
    parts: int,
) -> None:
    """KeepawaySimulator.reset on the ``mask`` fields: a new episode drawn from
    each field's own generator, in place (the other fields, and every clock, stay as they are)."""
    batch = pos.shape[0]
    for p in numba.prange(parts):
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            if mask[b]:
                _reset_field(
                    b,
                    pos,
                    vel,
                    body,
                    counter,
                    ep,
                    last_dec,
                    prev_holder,
                    pass_target,
                    action_start,
                    spos,
                    svel,
                    sbody,
                    rng,
                    prm,
                    ip,
                )


@_PAR
def env_outputs(
    pos: np.ndarray,
    body: np.ndarray,
    ep: np.ndarray,
    last_dec: np.ndarray,
    prev_holder: np.ndarray,
    pass_target: np.ndarray,
    action_start: np.ndarray,
    clock: np.ndarray,
    phase: np.ndarray,
    spos: np.ndarray,
    fields: np.ndarray,
    cause: np.ndarray,
    cycles: np.ndarray,
    stepping: bool,
    prm: np.ndarray,
    ip: np.ndarray,
    obs_out: np.ndarray,
    keeper_out: np.ndarray,
    mask_out: np.ndarray,
    ep_out: np.ndarray,
    cause_out: np.ndarray,
    end_rewards_out: np.ndarray,
    step_cycles_out: np.ndarray,
    deciding_out: np.ndarray,
    done: np.ndarray,
    reward_out: np.ndarray,
    parts: int,
) -> None:
    """KeepawayEnv's outputs, in place, after a step (``stepping``: the
    ``fields`` were alive and advanced, ``cause`` [B] how they ended, ``cycles`` [B] how long they ran;
    ``reward_out`` [B] the step's reward) or after a reset of the ``fields``: the observation, keeper,
    action mask and episode cycles of those fields, their end cause, end rewards and step cycles, the
    ``done`` flags and, for every field, whether it decides now."""
    batch = pos.shape[0]
    for p in numba.prange(parts):
        n = ip[N]
        kpos, tpos, order, obs = view_work(ip, obs_out.shape[1])
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            h, _, must = _decision(
                b, pos, clock, phase, spos, pass_target, prev_holder, ep, action_start, prm, ip
            )
            here = fields[b]
            if stepping:
                ended = cause[b] != 0
                reward = 0
                if ended:
                    latest = -1
                    for k in range(n):
                        latest = max(latest, last_dec[b, k])
                    reward = ep[b] - latest if latest >= 0 else ep[b]
                    done[b] = True
                    cause_out[b] = cause[b]
                    for k in range(n):
                        end_rewards_out[b, k] = ep[b] - last_dec[b, k] if last_dec[b, k] >= 0 else 0
                elif here:
                    if must and last_dec[b, h] >= 0:
                        reward = ep[b] - last_dec[b, h]
                    cause_out[b] = 0
                    for k in range(n):
                        end_rewards_out[b, k] = 0.0
                reward_out[b] = reward
                step_cycles_out[b] = cycles[b] if here else 0
            elif here:
                cause_out[b] = 0
                for k in range(n):
                    end_rewards_out[b, k] = 0.0
                step_cycles_out[b] = 0
                done[b] = False
            if here:
                _view(b, h, pos, body, spos, ip, kpos, tpos)
                _state_vars(kpos, tpos, h, order, obs)
                for i in range(obs.shape[0]):
                    obs_out[b, i] = obs[i]
                keeper_out[b] = h
                for a in range(mask_out.shape[1]):
                    mask_out[b, a] = True
                ep_out[b] = ep[b]
            deciding_out[b] = must and not done[b]
