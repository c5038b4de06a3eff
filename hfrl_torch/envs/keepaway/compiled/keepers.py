"""keepers.py in compiled code: the keepers' interceptions on a view, the fastest keeper and each
keeper's command (the holder's HoldBall or PassBall, GoToBall for the fastest, GetOpen for the others)."""

from __future__ import annotations

from hfrl_torch.envs.keepaway.compiled.common import _FI, B_DECAY, HORIZON, NO_CAP, T_TRAVEL, M, N, _hyp
from hfrl_torch.envs.keepaway.compiled.skills import (
    _face,
    _get_open_point,
    _hold,
    _intercept,
    _intercept_move,
    _move_to,
    _pass,
)
from hfrl_torch.envs.keepaway.skills import GET_OPEN_BUFFER, GOAL_X, HOLD_RATIO_KEEPER, WHEN_TO_TURN


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
        return _hold(me, vpos, vvel, vbody, 1 + n, ip[M], HOLD_RATIO_KEEPER, GOAL_X, prm, ip)
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
    if _hyp(px - tx, py - ty) < GET_OPEN_BUFFER:
        return _face(px, py, vx, vy, body, bx, by, prm)
    return _move_to(px, py, vx, vy, body, tx, ty, WHEN_TO_TURN, prm)
