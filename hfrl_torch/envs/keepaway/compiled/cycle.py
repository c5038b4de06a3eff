"""simulator.py's cycle in compiled code, per field: the decision, every player's command (on the
exact state or each on its own world model), then physics, referee and world models in the torch
path's order."""

from __future__ import annotations

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import (
    _F,
    KD,
    NO_CAP,
    NOISE,
    O_HELD,
    PERIOD,
    S_BODY,
    S_CMD,
    S_ICYC,
    S_IPTS,
    S_KPOS,
    S_OPEN,
    S_ORDER,
    S_POS,
    S_TPOS,
    S_TPTS,
    S_VEL,
    SERVER_PERCEPTION,
    SERVER_TIMING,
    M,
    N,
    _hyp,
)
from hfrl_torch.envs.keepaway.compiled.keepers import _fastest, _keeper_command, _keeper_intercepts
from hfrl_torch.envs.keepaway.compiled.perception import _predict_beliefs, _see, _sees
from hfrl_torch.envs.keepaway.compiled.physics import _move
from hfrl_torch.envs.keepaway.compiled.referee import _referee
from hfrl_torch.envs.keepaway.compiled.skills import _intercept
from hfrl_torch.envs.keepaway.compiled.state_vars import _order, _view
from hfrl_torch.envs.keepaway.compiled.takers import _taker_command


@_F
def _decision(b, st, prm, ip):
    """KeepawaySimulator.decision for field ``b``: (holder, kickable, must_decide)."""
    pos, spos, pass_target = st.pos, st.seen_pos, st.pass_target
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
        if _sees(st.clock[b], st.see_phase[b, holder]):
            passing = False
    holding = pass_target[b] < 0 and st.episode_cycles[b] - st.action_start[b] < ip[PERIOD]
    running = st.prev_holder[b] == holder and (passing or holding)
    return holder, kickable, kickable and not running


@_F
def _commands(b, st, holder, kickable, pass_target, prm, ip, tabs, scr):
    """Every player's command [P, 3] (kind, power, angle) of field ``b`` into ``scr``'s first array."""
    n, m = ip[N], ip[M]
    cmd, icyc, ipts, tpts, opn = scr[S_CMD], scr[S_ICYC], scr[S_IPTS], scr[S_TPTS], scr[S_OPEN]
    opn[O_HELD, 0] = 0.0
    if ip[SERVER_PERCEPTION] == 0:
        vpos, vvel, vbody = st.pos[b], st.vel[b], st.body[b]
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
    spos, svel, sbody = st.seen_pos, st.seen_vel, st.seen_body
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


@_F
def _cycle(b, st, action, u, prm, ip, tabs, scr):
    """KeepawaySimulator.step for field ``b`` (active), the holder reading ``action`` if it must
    decide; ``u`` its uniforms in the torch path's order, ``scr`` the :func:`scratch` arrays.
    Returns the end cause (0 running)."""
    n, m = ip[N], ip[M]
    players = n + m
    objects = 1 + players
    pass_target, ep, last_dec = st.pass_target, st.episode_cycles, st.last_decision
    prev_holder = st.prev_holder
    holder, kickable, must = _decision(b, st, prm, ip)
    if must:
        target = -1
        if action > 0:
            kpos, tpos, order = scr[S_KPOS], scr[S_TPOS], scr[S_ORDER]
            _view(b, holder, st, ip, kpos, tpos)
            _order(kpos, holder, order)
            target = order[min(max(action, 1), n - 1) - 1]
        pass_target[b] = target
        st.action_start[b] = ep[b]
        last_dec[b, holder] = ep[b]
    if not kickable:
        pass_target[b] = -1
    _commands(b, st, holder, kickable, pass_target[b], prm, ip, tabs, scr)
    cmd = scr[S_CMD]

    # physics (the old positions stay in the state until the end: the world models need them)
    _move(b, st, cmd, u, prm, ip, scr)
    new_pos, new_vel, new_body = scr[S_POS], scr[S_VEL], scr[S_BODY]
    cause = _referee(b, st.counter, new_pos, prm, ip)

    # world models: extrapolate from the old belief and the own command, then see the new state
    server = ip[SERVER_PERCEPTION] != 0
    if server:
        _predict_beliefs(b, st, cmd, new_vel, new_body, prm, ip)
    pos, vel, body = st.pos, st.vel, st.body
    for o in range(objects):
        pos[b, o, 0], pos[b, o, 1] = new_pos[o, 0], new_pos[o, 1]
        vel[b, o, 0], vel[b, o, 1] = new_vel[o, 0], new_vel[o, 1]
        body[b, o] = new_body[o]
    ep[b] += 1
    st.clock[b] += 1
    if server:
        u_seen = 3 * players + 2 * objects if ip[NOISE] != 0 else 0
        _see(b, st, u, u_seen, prm, ip)
    prev_holder[b] = holder if kickable else -1
    if ip[SERVER_TIMING] != 0:
        h2, k2, _ = _decision(b, st, prm, ip)
        if k2 and prev_holder[b] == h2 and pass_target[b] >= 0:
            last_dec[b, h2] = ep[b]
    return cause
