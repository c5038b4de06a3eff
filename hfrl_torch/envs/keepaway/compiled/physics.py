"""physics.py in compiled code, per field: the kick power rate, the players' commands applied (kicks,
dashes, turns, with the server's noise), movement and collision resolution."""

from __future__ import annotations

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import (
    _FI,
    B_ACC,
    B_DECAY,
    B_RAND,
    B_SIZE,
    B_SPEED,
    DASH_RATE,
    INERTIA,
    KD,
    KICK_RAND,
    KICK_RATE,
    MARGIN,
    MAX_MOMENT,
    MAX_POWER,
    MIN_DASH,
    NOISE,
    P_ACC,
    P_DECAY,
    P_RAND,
    P_SIZE,
    P_SPEED,
    PASSES,
    PI,
    POLAR,
    S_ACC,
    S_BODY,
    S_HIT,
    S_POS,
    S_VEL,
    M,
    N,
    _hyp,
    _wrap,
)
from hfrl_torch.envs.keepaway.physics import (
    COLLISION_BOUNCE,
    COLLISION_SLACK,
    DASH_KIND,
    KICK_KIND,
    PAIR_FALLBACK_STEP,
    TURN_KIND,
)


@_FI
def _kick_rate(px, py, body, bx, by, prm):
    rx, ry = bx - px, by - py
    dir_diff = abs(_wrap(np.arctan2(ry, rx) - body))
    gap = _hyp(rx, ry) - prm[P_SIZE] - prm[B_SIZE]
    return prm[KICK_RATE] * (1.0 - 0.25 * dir_diff / PI - 0.25 * gap / prm[MARGIN])


@_FI
def _move(b, st, cmd, u, prm, ip, scr):
    """The commands ``cmd`` [P, 3] of field ``b`` applied and every object moved (with noise from ``u``
    in the torch path's order): the new positions, velocities and bodies into ``scr``; the state
    itself is not changed (the world models read the old one)."""
    pos, vel, body = st.pos, st.vel, st.body
    players = ip[N] + ip[M]
    objects = 1 + players
    noise = ip[NOISE] != 0
    u_kick, u_turn, u_move = 0, 2 * players, 3 * players
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
        if kind == KICK_KIND:
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
        elif kind == DASH_KIND:
            pw = min(max(power, prm[MIN_DASH]), prm[MAX_POWER]) * prm[DASH_RATE]
            acc[o, 0], acc[o, 1] = pw * np.cos(pb), pw * np.sin(pb)
        new_body[o] = pb
        if kind == TURN_KIND:
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
    _collide(new_pos, new_vel, hit, objects, prm, ip)


@_FI
def _collide(new_pos, new_vel, hit, objects, prm, ip):
    """physics.resolve_collisions on the moved objects, in place: pairs in order, at most ``PASSES``
    passes; every collided object's velocity reversed and damped once."""
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
                        a = k * PAIR_FALLBACK_STEP
                        ax, ay = np.cos(a), np.sin(a)
                    push = 0.5 * (contact - dist) + COLLISION_SLACK
                    new_pos[i, 0] -= push * ax
                    new_pos[j, 0] += push * ax
                    new_pos[i, 1] -= push * ay
                    new_pos[j, 1] += push * ay
                    hit[i] = True
                    hit[j] = True
                k += 1
    for o in range(objects):
        if hit[o]:
            new_vel[o, 0] *= COLLISION_BOUNCE
            new_vel[o, 1] *= COLLISION_BOUNCE
