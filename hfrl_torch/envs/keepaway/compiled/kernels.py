"""The entry points of the compiled keepaway cycle, called by glue.py with the state as one
:class:`~hfrl_torch.envs.keepaway.compiled.common.CycleState`: one cycle with the torch path's uniforms,
the decisions and observations, the SMDP advances (``sync="all"`` and ``"any"``), the benchmark
keepers' play, the resets and the env's outputs.

Each splits the fields into ``parts`` contiguous ranges, one per thread (numba's ``prange`` over the
ranges; glue.py picks ``parts``): OpenMP's workers take a range in microseconds, where a Python thread
pool's hand-off cost 75-150 us on this VM, which ate the gain of splitting one cycle."""

from __future__ import annotations

import numba
import numpy as np

from hfrl_torch.common.threads import part_range
from hfrl_torch.envs.keepaway.compiled.common import (
    _PAR,
    CycleState,
    M,
    N,
    _fill,
    scratch,
    uniform_count,
    view_work,
)
from hfrl_torch.envs.keepaway.compiled.cycle import _cycle, _decision
from hfrl_torch.envs.keepaway.compiled.policies import HOLD, _policy_action
from hfrl_torch.envs.keepaway.compiled.referee import _reset_field
from hfrl_torch.envs.keepaway.compiled.state_vars import _observation, _state_vars, _view


@_PAR
def cycle(
    st: CycleState,
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
    batch = st.pos.shape[0]
    for p in numba.prange(parts):
        scr = scratch(ip, grid)
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            cause_out[b] = 0
            if active[b]:
                cause_out[b] = _cycle(b, st, actions[b], u[b], prm, ip, tabs, scr)


@_PAR
def decisions(
    st: CycleState,
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
    batch = st.pos.shape[0]
    for p in numba.prange(parts):
        kpos, tpos, order, obs = view_work(ip, obs_out.shape[1])
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            h, k, must = _decision(b, st, prm, ip)
            holder_out[b], kickable_out[b], must_out[b] = h, k, must
            _observation(b, h, st, ip, kpos, tpos, order, obs, obs_out)


@_PAR
def observations(
    st: CycleState,
    decider: np.ndarray,
    ip: np.ndarray,
    obs_out: np.ndarray,
    order_out: np.ndarray,
    parts: int,
) -> None:
    """The state variables of keeper ``decider[b]`` on every field and its teammate order, as the
    compiled cycle numbers the teammates (its PassBall k goes to ``order_out[b, k - 1]``)."""
    batch = st.pos.shape[0]
    for p in numba.prange(parts):
        kpos, tpos, _, obs = view_work(ip, obs_out.shape[1])
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            _observation(b, decider[b], st, ip, kpos, tpos, order_out[b], obs, obs_out)


@_PAR
def advance_fields(
    st: CycleState,
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
    """Each ``running`` field on its own up to its holder's next decision: a first cycle with
    ``actions`` where ``first``, then cycles until the holder must decide or the episode ends
    (restarted and played on where ``restart``). ``cycles_out`` counts the cycles, ``cause_out``
    the end cause (0 where none). Returns the number of fields that hit ``max_cycles``."""
    batch = st.pos.shape[0]
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
                    _, _, must = _decision(b, st, prm, ip)
                    if must:
                        done = True
                        break
                _fill(rng, b, u)
                cause = _cycle(b, st, actions[b] if go else 0, u, prm, ip, tabs, scr)
                go = False
                cycles_out[b] += 1
                if cause != 0:
                    if restart:
                        _reset_field(b, st, rng, prm, ip)
                    else:
                        cause_out[b] = cause
                        done = True
                        break
            if not done:
                stuck[p] += 1
    return stuck.sum()


@_PAR
def _any_cycle(
    st: CycleState,
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
    batch = st.pos.shape[0]
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
            cause = _cycle(b, st, actions[b] if go[b] else 0, u, prm, ip, tabs, scr)
            cause_out[b] = cause
            if cause == 0:
                _, _, must = _decision(b, st, prm, ip)
                must_out[b] = must


@numba.njit(cache=True, nogil=True)
def advance_any(
    st: CycleState,
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
    batch = st.pos.shape[0]
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
            _, _, must[b] = _decision(b, st, prm, ip)
    for _ in range(max_cycles + 1):
        if check:
            stop = False
            for b in range(batch):
                if alive[b] and must[b]:
                    stop = True
            if stop:
                return True
        _any_cycle(st, rng, actions, go, alive, prm, ip, tabs, grid, step_cause, must, parts)
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
    st: CycleState,
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
    """Benchmark keepers (``policy``: policies.HOLD, RANDOM or HAND) deciding inside each cycle, on
    every field until it has played ``durations.shape[1]`` episodes or ``max_cycles`` cycles; each
    ended episode's length and cause are stored, and the next one starts at once. Returns the
    field-cycles simulated."""
    batch = st.pos.shape[0]
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
                if policy != HOLD:
                    h, _, must = _decision(b, st, prm, ip)
                    if must:
                        _view(b, h, st, ip, kpos, tpos)
                        _state_vars(kpos, tpos, h, order, obs64)
                        for i in range(obs.shape[0]):
                            obs[i] = obs64[i]
                        action = _policy_action(policy, obs, rng, b, ip)
                _fill(rng, b, u)
                cause = _cycle(b, st, action, u, prm, ip, tabs, scr)
                total[p] += 1
                if cause != 0:
                    durations[b, played[b]] = st.episode_cycles[b]
                    causes[b, played[b]] = cause
                    played[b] += 1
                    _reset_field(b, st, rng, prm, ip)
    return total.sum()


@_PAR
def reset_fields(
    st: CycleState, rng: np.ndarray, mask: np.ndarray, prm: np.ndarray, ip: np.ndarray, parts: int
) -> None:
    """KeepawaySimulator.reset on the ``mask`` fields: a new episode drawn from
    each field's own generator, in place (the other fields, and every clock, stay as they are)."""
    batch = st.pos.shape[0]
    for p in numba.prange(parts):
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            if mask[b]:
                _reset_field(b, st, rng, prm, ip)


@_PAR
def env_outputs(
    st: CycleState,
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
    batch = st.pos.shape[0]
    ep, last_dec = st.episode_cycles, st.last_decision
    for p in numba.prange(parts):
        n = ip[N]
        kpos, tpos, order, obs = view_work(ip, obs_out.shape[1])
        lo, hi = part_range(batch, p, parts)
        for b in range(lo, hi):
            h, _, must = _decision(b, st, prm, ip)
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
                _view(b, h, st, ip, kpos, tpos)
                _state_vars(kpos, tpos, h, order, obs)
                for i in range(obs.shape[0]):
                    obs_out[b, i] = obs[i]
                keeper_out[b] = h
                for a in range(mask_out.shape[1]):
                    mask_out[b, a] = True
                ep_out[b] = ep[b]
            deciding_out[b] = must and not done[b]
