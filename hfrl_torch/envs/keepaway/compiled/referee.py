"""referee.py in compiled code, per field: the end of a cycle (ball out of the region, the takers'
possession counter) and the coach's reset of an episode (simulator.fresh_state's draws, from the
field's own random stream)."""

from __future__ import annotations

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import (
    _FA,
    _FI,
    KD,
    LENGTH,
    SERVER_PERCEPTION,
    TURNOVER,
    WIDTH,
    M,
    N,
    _hyp,
    _next,
)
from hfrl_torch.envs.keepaway.compiled.perception import _observe, _own_truth
from hfrl_torch.envs.keepaway.referee import BALL_START_INSET, CORNER_SPREAD, END_OUT, END_RUNNING, END_TAKEN


@_FI
def _referee(b, counter, new_pos, prm, ip):
    """referee.update_turnover_counter and referee.end_cause for field ``b`` with the objects at
    ``new_pos`` [O, 2]: the counter updated in place; the end cause."""
    n, m = ip[N], ip[M]
    kd = prm[KD]
    nbx, nby = new_pos[0, 0], new_pos[0, 1]
    keeper_near, taker_near = False, False
    for o in range(1, 1 + n + m):
        if _hyp(new_pos[o, 0] - nbx, new_pos[o, 1] - nby) <= kd:
            if o <= n:
                keeper_near = True
            else:
                taker_near = True
    if taker_near:
        counter[b] += 1
    elif keeper_near:
        counter[b] = 0
    cause = END_RUNNING
    if not (abs(nbx) < 0.5 * prm[LENGTH] and abs(nby) < 0.5 * prm[WIDTH]):
        cause = END_OUT
    elif counter[b] >= ip[TURNOVER]:
        cause = END_TAKEN
    return cause


@_FA
def _reset_field(b, st, rng, prm, ip):
    """KeepawaySimulator.fresh_state for field ``b``, drawn from its own generator (referee.reset_positions'
    layout); its clock and see phases stay."""
    pos, vel = st.pos, st.vel
    n, m = ip[N], ip[M]
    hx, hy = 0.5 * prm[LENGTH], 0.5 * prm[WIDTH]
    k0 = min(np.int64(_next(rng, b) * n), n - 1)
    for i in range(n):
        u1, u2 = _next(rng, b), _next(rng, b)
        slot = (k0 + i) % n
        if slot < 3:
            sx = -1.0 if slot == 0 else 1.0
            sy = 1.0 if slot == 2 else -1.0
            pos[b, 1 + i, 0] = sx * (hx - CORNER_SPREAD * u1)
            pos[b, 1 + i, 1] = sy * (hy - CORNER_SPREAD * u2)
        else:
            pos[b, 1 + i, 0], pos[b, 1 + i, 1] = 2.0 * u1 - 1.0, 2.0 * u2 - 1.0
    for j in range(m):
        u1, u2 = _next(rng, b), _next(rng, b)
        pos[b, 1 + n + j, 0], pos[b, 1 + n + j, 1] = -(hx - CORNER_SPREAD * u1), hy - CORNER_SPREAD * u2
    pos[b, 0, 0], pos[b, 0, 1] = -hx + BALL_START_INSET, -hy + BALL_START_INSET
    for o in range(1 + n + m):
        vel[b, o, 0], vel[b, o, 1] = 0.0, 0.0
    st.counter[b] = 0
    st.episode_cycles[b] = 0
    for k in range(n):
        st.last_decision[b, k] = -1
    st.prev_holder[b] = -1
    st.pass_target[b] = -1
    st.action_start[b] = 0
    if ip[SERVER_PERCEPTION] != 0:
        svel = st.seen_vel
        for p in range(n + m):
            for o in range(1 + n + m):
                svel[b, p, o, 0], svel[b, p, o, 1] = 0.0, 0.0
            _observe(b, p, st, np.empty(1), 0, False, prm, ip)
            _own_truth(b, p, st)
