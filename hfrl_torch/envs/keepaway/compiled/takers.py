"""takers.py in compiled code: a taker's command on a view (Hand-coded-T: the nearest takes the ball and
holds it, the next goes to the ball, any further one blocks the pass to the most open keeper)."""

from __future__ import annotations

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import _FI, KD, M, N, _hyp
from hfrl_torch.envs.keepaway.compiled.skills import _block_point, _face, _hold, _intercept_move, _move_to
from hfrl_torch.envs.keepaway.skills import GOAL_X, HOLD_RATIO_TAKER, MARK_BUFFER, MARK_TURN


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
        return _hold(me, vpos, vvel, vbody, 1, n, HOLD_RATIO_TAKER, -GOAL_X, prm, ip)
    if m > 2 and rank >= 2:
        tx, ty = _block_point(vpos, with_ball, ip)
        if _hyp(px - tx, py - ty) < MARK_BUFFER:
            return _face(px, py, vx, vy, body, bx, by, prm)
        return _move_to(px, py, vx, vy, body, tx, ty, MARK_TURN, prm)
    keeper_near = np.inf
    for k in range(n):
        keeper_near = min(keeper_near, _hyp(vpos[1 + k, 0] - bx, vpos[1 + k, 1] - by))
    if nearest < keeper_near and nearest <= kd and rank != 0:
        return _face(px, py, vx, vy, body, bx, by, prm)
    return _intercept_move(px, py, vx, vy, body, tcyc_pts[j, 0], tcyc_pts[j, 1], bx, by, prm)
