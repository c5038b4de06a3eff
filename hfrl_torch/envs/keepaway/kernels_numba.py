"""Compiled (numba) kernels of three searches of a keepaway cycle, the CPU fast path.

GoToBall's interception search and GetOpen's choice of grid point evaluate [H + 1] and [25]
candidates per player, and the collision passes go through the object pairs in order; as tensor
ops they were a third of a cycle's time on CPU, as loops they stop at the first reachable cycle
(or the first pass without overlap) and keep everything in registers. Each kernel does
the torch path's float arithmetic in the same order (no fused multiply-adds, sums left to right),
so both paths give the same bits: ``tests/envs/keepaway/test_keepaway_kernels.py`` checks it, on
single calls and on whole simulated episodes. The kernels take float32 arrays (the simulator's
dtype); a float64 simulator runs the torch path.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def intercept_search(
    pos: np.ndarray,
    vel: np.ndarray,
    hx: np.ndarray,
    hy: np.ndarray,
    ball_pos: np.ndarray,
    ball_vel: np.ndarray,
    cos_limits: np.ndarray,
    travel: np.ndarray,
    travel_sq: np.ndarray,
    series: np.ndarray,
    cruise_part: np.ndarray,
    table: np.ndarray,
    consts: np.ndarray,
    cycles_out: np.ndarray,
    points_out: np.ndarray,
) -> None:
    """``skills.intercept_estimate``: cycles [B, P] until each player can kick the ball, and where
    [B, P, 2]; the search stops at the first reachable look-ahead cycle.

    ``pos``, ``vel`` [B, P, 2]; body direction ``hx``, ``hy`` [B, P]; ball [B, 2];
    ``cos_limits`` [3, B, P]; per-cycle terms [H + 1]; ``table`` [4, H + 1]; ``consts`` =
    (kickable distance, 1e-12, 0, 1, 2, dash acceleration, speed cap, cruise speed,
    1 - ball decay).
    """
    kickable, tiny, zero, one, two = consts[0], consts[1], consts[2], consts[3], consts[4]
    accel, speed_max, cruise, still = consts[5], consts[6], consts[7], consts[8]
    batch, players = hx.shape
    cycles = travel.shape[0]
    for b in range(batch):
        bx, by = ball_pos[b, 0], ball_pos[b, 1]
        vx, vy = ball_vel[b, 0], ball_vel[b, 1]
        vsq = vx * vx + vy * vy
        for p in range(players):
            dx = bx - pos[b, p, 0]
            dy = by - pos[b, p, 1]
            ex = dx - vel[b, p, 0]
            ey = dy - vel[b, p, 1]
            need_lin = two * (dx * vx + dy * vy)
            need_const = dx * dx + dy * dy
            err_lin = two * (ex * vx + ey * vy)
            err_const = ex * ex + ey * ey + tiny
            head_lin = vx * hx[b, p] + vy * hy[b, p]
            head_const = ex * hx[b, p] + ey * hy[b, p]
            forward = vel[b, p, 0] * hx[b, p] + vel[b, p, 1] * hy[b, p]
            if forward < zero:
                forward = zero
            first = forward + accel
            if first > speed_max:
                first = speed_max
            first_gap = first - cruise
            found = -1
            for i in range(cycles):
                moved = travel_sq[i] * vsq
                need = travel[i] * need_lin + need_const + moved
                if need < zero:
                    need = zero
                need = np.sqrt(need) - kickable
                err = travel[i] * err_lin + err_const + moved
                if err < tiny:
                    err = tiny
                err = (one / np.sqrt(err)) * (travel[i] * head_lin + head_const)
                if err >= cos_limits[0, b, p]:
                    reach = series[i] * first_gap + cruise_part[i]
                elif err >= cos_limits[1, b, p]:
                    reach = table[1, i]
                elif err >= cos_limits[2, b, p]:
                    reach = table[2, i]
                else:
                    reach = table[3, i]
                if need <= reach:
                    found = i
                    break
            if found >= 0:
                cycles_out[b, p] = found
                points_out[b, p, 0] = bx + travel[found] * vx
                points_out[b, p, 1] = by + travel[found] * vy
            else:
                rx = bx + vx / still
                ry = by + vy / still
                run = _hypot(rx - pos[b, p, 0], ry - pos[b, p, 1]) / cruise
                cycles_out[b, p] = cycles + np.int64(np.ceil(run))
                points_out[b, p, 0] = rx
                points_out[b, p, 1] = ry


@numba.njit(cache=True, nogil=True)
def least_congested_points(
    grid: np.ndarray,
    players: np.ndarray,
    pass_from: np.ndarray,
    keepers: int,
    consts: np.ndarray,
    choice: np.ndarray,
    none_open: np.ndarray,
) -> None:
    """GetOpen's grid point [B, n] for every keeper, and whether every pass cone is blocked [B].

    ``grid`` [C, 2]; ``players`` [B, P, 2], keepers first, then takers; ``pass_from`` [B, 2];
    ``consts`` = (1 + cone width^2, 1e-12, blocked penalty, 0, 1) in the arrays' dtype.
    """
    cone, tiny, penalty, zero, one = consts[0], consts[1], consts[2], consts[3], consts[4]
    batch, everyone = players.shape[0], players.shape[1]
    candidates = grid.shape[0]
    inv = np.empty(everyone, dtype=players.dtype)
    for b in range(batch):
        best = np.full(keepers, np.inf, dtype=players.dtype)
        all_blocked = True
        for c in range(candidates):
            sx = grid[c, 0] - pass_from[b, 0]
            sy = grid[c, 1] - pass_from[b, 1]
            seg_sq = sx * sx + sy * sy
            blocked = False
            for t in range(keepers, everyone):
                rx = players[b, t, 0] - pass_from[b, 0]
                ry = players[b, t, 1] - pass_from[b, 1]
                along = rx * sx + ry * sy
                rel_sq = rx * rx + ry * ry
                if (
                    rel_sq * seg_sq < cone * along * along
                    and along >= zero
                    and along <= seg_sq
                    and rel_sq < seg_sq
                ):
                    blocked = True
            if not blocked:
                all_blocked = False
            total = zero
            for q in range(everyone):
                dx = grid[c, 0] - players[b, q, 0]
                dy = grid[c, 1] - players[b, q, 1]
                inv[q] = one / np.sqrt(dx * dx + dy * dy + tiny)
                total += inv[q]
            extra = penalty if blocked else zero
            for k in range(keepers):
                congestion = total - inv[k] + extra
                if congestion < best[k]:
                    best[k] = congestion
                    choice[b, k] = c
        none_open[b] = all_blocked


@numba.njit(cache=True, nogil=True)
def push_apart(
    pos: np.ndarray,
    pairs: np.ndarray,
    contact: np.ndarray,
    check: np.ndarray,
    fallback: np.ndarray,
    max_passes: int,
    consts: np.ndarray,
    collided: np.ndarray,
) -> None:
    """``physics.resolve_collisions``'s passes over overlapping pairs, in place on ``pos`` [B, O, 2].

    ``pairs`` [K, 2] in the torch order; ``contact`` [K] the touching distance of a pair as the
    push uses it, ``check`` [K] as the pass test uses it; ``fallback`` [K, 2] the direction of a
    pair at one point; ``consts`` = (slack, 1e-9, 0.5, 1). Marks the objects that collided in
    ``collided`` [B, O] (cleared first).
    """
    slack, tiny, half, one = consts[0], consts[1], consts[2], consts[3]
    batch, objects = pos.shape[0], pos.shape[1]
    count = pairs.shape[0]
    for b in range(batch):
        for o in range(objects):
            collided[b, o] = False
        for _ in range(max_passes):
            any_overlap = False
            for k in range(count):
                i, j = pairs[k, 0], pairs[k, 1]
                if _hypot(pos[b, j, 0] - pos[b, i, 0], pos[b, j, 1] - pos[b, i, 1]) < check[k]:
                    any_overlap = True
                    break
            if not any_overlap:
                break
            for k in range(count):
                i, j = pairs[k, 0], pairs[k, 1]
                dx = pos[b, j, 0] - pos[b, i, 0]
                dy = pos[b, j, 1] - pos[b, i, 1]
                dist = _hypot(dx, dy)
                if not dist < contact[k]:
                    continue
                if dist > tiny:
                    inv = one / dist
                    ax, ay = dx * inv, dy * inv
                else:
                    ax, ay = fallback[k, 0], fallback[k, 1]
                push = half * (contact[k] - dist) + slack
                pos[b, i, 0] = pos[b, i, 0] - push * ax
                pos[b, j, 0] = pos[b, j, 0] + push * ax
                pos[b, i, 1] = pos[b, i, 1] - push * ay
                pos[b, j, 1] = pos[b, j, 1] + push * ay
                collided[b, i] = True
                collided[b, j] = True


@numba.njit(cache=True, inline="always")
def _hypot(x: float, y: float) -> float:
    """sqrt(x^2 + y^2) of float32 values in float64, rounded once to float32, as
    ``physics.hypot_f64`` on the torch path."""
    return np.float32(np.sqrt(np.float64(x) * np.float64(x) + np.float64(y) * np.float64(y)))
