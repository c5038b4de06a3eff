"""state_vars.py in compiled code: a keeper's view of the players (exact, its world model's, or the
quantised sensor's), its teammate order and its state variables."""

from __future__ import annotations

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import (
    _F,
    _FA,
    DEG,
    NOISY_OBS,
    SERVER_PERCEPTION,
    M,
    N,
    _hyp,
    _wrap,
)
from hfrl_torch.envs.keepaway.compiled.perception import _qdir, _qdist


@_F
def _view(b, decider, st, ip, kpos, tpos):
    """KeepawaySimulator._seen_positions: keepers [n, 2] and takers [m, 2] as ``decider`` sees them."""
    pos, body, spos = st.pos, st.body, st.seen_pos
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
def _observation(b, decider, st, ip, kpos, tpos, order, obs, obs_out):
    """Keeper ``decider``'s state variables on field ``b`` into ``obs_out[b]`` (``order`` keeps its
    teammate order)."""
    _view(b, decider, st, ip, kpos, tpos)
    _state_vars(kpos, tpos, decider, order, obs)
    for i in range(obs.shape[0]):
        obs_out[b, i] = obs[i]
