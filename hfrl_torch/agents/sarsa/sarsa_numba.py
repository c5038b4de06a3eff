"""SMDP Sarsa(lambda) in compiled code (numba): :class:`SarsaLambda`'s decisions and episode ends in one
call each, without torch's per-op overhead (tens of microseconds for a few rows; benchmarks/sarsa_decide.py).

:class:`SarsaLambdaNumba` keeps every piece of state in the torch tensors of :class:`SarsaLambda` (the
coder's ``weight``, ``last_action``, ``q_last``, ``trace_index``, ``trace_value``), read and written in
place through numpy views, so checkpoints, ``state_dict`` and a shared H^ see one truth. The three
uniform arrays of ``select`` are drawn in Python by the same torch generator calls in the same order, so
both learners choose the same actions; Q sums accumulate in float64 (torch's float32 ``sum`` uses other
partial sums), so weights, ``q_last`` and traces agree within float32 rounding.

Trace slots hold the same set of (tile, value) pairs as the torch learner's; their order may differ when
lambda > 0 (torch keeps a ``topk``'s order, here survivors are compacted first, then the fresh tiles).
With gamma * lambda < min_trace (the thesis's lambda = 0) the layout is torch's too: the chosen tiles
sorted, duplicates with value 0.
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np
import torch

from hfrl_torch.agents.sarsa.sarsa import SarsaLambda
from hfrl_torch.common.arrays import as_numpy
from hfrl_torch.common.threads import part_range, thread_count
from hfrl_torch.models.tile_coding import TileCoding
from hfrl_torch.models.tile_coding_numba import table_sums, tile_indices, tile_row, tile_sum

_JIT = numba.njit(cache=True, nogil=True)

# entries of the ``params`` array (in the weights' dtype, so the kernel computes in it as torch does)
STEP, GAMMA, DECAY, MIN_TRACE, EPSILON = range(5)
MIN_ROWS_PER_THREAD = (
    4  # decisions a second thread needs to gain (10-20 us a row, memory-bound; a prange region 4-11 us)
)


@_JIT
def _argmax_first(values: np.ndarray) -> int:
    """Index of the first largest entry (torch's ``argmax`` on ties)."""
    best, at = values[0], 0
    for i in range(1, values.shape[0]):
        if values[i] > best:
            best, at = values[i], i
    return at


@_JIT
def _select(
    choose: np.ndarray,
    mask: np.ndarray,
    tie: np.ndarray,
    noise: np.ndarray,
    draw: float,
    epsilon: float,
    explore: bool,
) -> int:
    """``SarsaLambda.select`` for one row from its three draws."""
    a = choose.shape[0]
    best = -np.inf
    for i in range(a):
        if mask[i] and choose[i] > best:
            best = choose[i]
    scores = np.empty(a, dtype=tie.dtype)
    for i in range(a):
        scores[i] = tie[i] if mask[i] and choose[i] == best else -1.0
    greedy = _argmax_first(scores)
    if not explore or not draw < epsilon:
        return greedy
    for i in range(a):
        scores[i] = noise[i] if mask[i] else -1.0
    return _argmax_first(scores)


@_JIT
def _distinct(learners: np.ndarray) -> bool:
    """Whether no learner is named twice."""
    s = np.sort(learners)
    for i in range(1, s.shape[0]):
        if s[i] == s[i - 1]:
            return False
    return True


@_JIT
def _sort_tiles(tiles: np.ndarray) -> np.ndarray:
    """Tile indices (>= 0) sorted ascending: a least-significant-digit radix sort with the digit width
    that costs least for this many keys and this largest key (one action's 416 tiles below 2^20: three
    passes of 7 bits: 1.3 us, against 2.3 us for two passes of 11 and 3.0 us for numba's quicksort)."""
    n = tiles.shape[0]
    out, spare = tiles.copy(), np.empty_like(tiles)
    top = 0
    for i in range(n):
        top = max(top, out[i])
    bits = 0
    while top >> bits > 0:
        bits += 1
    best, digit = 1 << 62, 1
    for d in range(1, 17):  # a pass touches 2^d buckets twice and the n keys twice
        cost = ((bits + d - 1) // d) * (2 * (1 << d) + 2 * n)
        if cost < best:
            best, digit = cost, d
    buckets = 1 << digit
    low = buckets - 1
    counts = np.empty(buckets + 1, dtype=np.int64)
    shift = 0
    while shift < bits:
        counts[:] = 0
        for i in range(n):
            counts[((out[i] >> shift) & low) + 1] += 1
        for d in range(buckets):
            counts[d + 1] += counts[d]
        for i in range(n):
            d = (out[i] >> shift) & low
            spare[counts[d]] = out[i]
            counts[d] += 1
        out, spare = spare, out
        shift += digit
    return out


@_JIT
def _add_traced(w: np.ndarray, index: np.ndarray, value: np.ndarray, scale) -> None:
    """``w[index[c]] += scale * value[c]`` over the nonzero slots (line 17)."""
    for c in range(index.shape[0]):
        v = value[c]
        if v != 0:
            w[index[c]] += scale * v


@_JIT
def _replace_traces(
    index: np.ndarray,
    value: np.ndarray,
    tiles: np.ndarray,
    mask: np.ndarray,
    action: int,
    starting: bool,
    params: np.ndarray,
    skip_matching: bool,
) -> None:
    """Lines 19-25 for one learner's slots, in place: decay and drop, clear the other available actions'
    tiles, set the chosen action's to 1 (deduplicated), keeping the ``capacity`` largest traces."""
    capacity = index.shape[0]
    n = tiles.shape[1]
    fresh = _sort_tiles(tiles[action])
    if skip_matching or starting:  # no older trace survives: torch's layout exactly
        for c in range(capacity):
            if c < n:
                index[c] = fresh[c]
                value[c] = 1.0 if c == 0 or fresh[c] != fresh[c - 1] else 0.0
            else:
                index[c] = 0
                value[c] = 0.0
        return
    decay, min_trace = params[DECAY], params[MIN_TRACE]
    a = tiles.shape[0]
    others = 0
    for i in range(a):
        if mask[i] and i != action:
            others += 1
    clear = np.empty((others + 1) * n, dtype=np.int64)
    k = 0
    for i in range(a):
        if mask[i] and i != action:
            clear[k * n : (k + 1) * n] = tiles[i]
            k += 1
    clear[k * n :] = fresh
    clear = _sort_tiles(clear)
    kept = 0
    for c in range(capacity):
        v = value[c] * decay
        if v < min_trace:
            continue
        t = index[c]
        at = np.searchsorted(clear, t)
        if at < clear.shape[0] and clear[at] == t:
            continue
        index[kept] = t
        value[kept] = v
        kept += 1
    unique = 1
    for i in range(1, n):
        if fresh[i] != fresh[i - 1]:
            unique += 1
    room = capacity - unique
    if kept > room:  # full: drop the smallest traces first
        order = np.argsort(-value[:kept], kind="mergesort")[:room]
        order = np.sort(order)
        for j in range(room):
            index[j] = index[order[j]]
            value[j] = value[order[j]]
        kept = room
    for i in range(n):
        if i == 0 or fresh[i] != fresh[i - 1]:
            index[kept] = fresh[i]
            value[kept] = 1.0
            kept += 1
    for c in range(kept, capacity):
        index[c] = 0
        value[c] = 0.0


# The decision in phases over row ranges, split over ``parts`` threads in ``prange`` regions (one range, so
# no split, where ``thread_count`` gives one thread): the reads by row range, then the traced updates split
# by weight table (each table's adds keep their row order), then the new Q_LastAction and traces, bit for
# bit as on one thread. OpenMP's workers take a region in a few microseconds; the Python thread pool this
# replaced cost 75-150 us a hand-off on this VM, three times a decision.


@numba.njit(cache=True, nogil=True, parallel=True)
def decide_rows(
    parts: int,
    weight: np.ndarray,
    widths: np.ndarray,
    shape: np.ndarray,
    tables: np.ndarray,
    learners: np.ndarray,
    obs: np.ndarray,
    with_states: bool,
    tiles: np.ndarray,
    q: np.ndarray,
    choose: np.ndarray,
    mask: np.ndarray,
    reward: np.ndarray,
    tie: np.ndarray,
    noise: np.ndarray,
    draw: np.ndarray,
    params: np.ndarray,
    explore: bool,
    skip_matching: bool,
    last_action: np.ndarray,
    q_last: np.ndarray,
    trace_index: np.ndarray,
    trace_value: np.ndarray,
    action: np.ndarray,
    chosen: np.ndarray,
) -> bool:
    """``SarsaLambda.decide`` of rows ``learners`` [M]: their ``tiles`` [M, A, N] and ``q`` [M, A] filled
    from the states ``obs`` [M, F] (``with_states``; ``shape``: tilings, actions, size) or the caller's
    (``decide(values=...)``); choose by ``choose`` [M, A], update every table from the same weights, then
    Q_LastAction and traces. False (and nothing changed) when the rows do not name distinct learners."""
    if not _distinct(learners):
        return False
    m = learners.shape[0]
    if with_states:
        for p in numba.prange(parts):
            lo, hi = part_range(m, p, parts)
            states_phase(weight, widths, shape, tables, learners, obs, tiles, q, lo, hi)
    delta = np.empty(m, dtype=weight.dtype)
    choose_phase(learners, q, choose, mask, reward, tie, noise, draw, params, explore,
                 last_action, q_last, action, delta, 0, m)  # lines 9-10, 16  # fmt: skip
    for p in numba.prange(parts):  # line 17, every row from the weights before this call
        update_phase(weight, tables, learners, params, last_action, trace_index, trace_value,
                     delta, parts, p, p + 1)  # fmt: skip
    for p in numba.prange(parts):  # lines 3, 18-25
        lo, hi = part_range(m, p, parts)
        finish_phase(weight, tables, learners, tiles, q, mask, params, skip_matching, last_action,
                     q_last, trace_index, trace_value, action, chosen, lo, hi)  # fmt: skip
    return True


@_JIT
def states_phase(
    weight: np.ndarray,
    widths: np.ndarray,
    shape: np.ndarray,
    tables: np.ndarray,
    learners: np.ndarray,
    obs: np.ndarray,
    tiles: np.ndarray,
    q: np.ndarray,
    lo: int,
    hi: int,
) -> None:
    """Tiles [M, A, N] and Q [M, A] (the weights' dtype, from float64 sums) of rows ``lo .. hi - 1``."""
    for r in range(lo, hi):
        tile_row(obs[r], widths, shape[0], shape[1], shape[2], tiles[r])
        w = weight[tables[learners[r]]]
        for c in range(tiles.shape[1]):
            q[r, c] = tile_sum(w, tiles[r, c])


@_JIT
def choose_phase(
    learners: np.ndarray,
    q: np.ndarray,
    choose: np.ndarray,
    mask: np.ndarray,
    reward: np.ndarray,
    tie: np.ndarray,
    noise: np.ndarray,
    draw: np.ndarray,
    params: np.ndarray,
    explore: bool,
    last_action: np.ndarray,
    q_last: np.ndarray,
    action: np.ndarray,
    delta: np.ndarray,
    lo: int,
    hi: int,
) -> None:
    """The action and TD error of rows ``lo .. hi - 1`` (lines 9-10, 16)."""
    gamma = params[GAMMA]
    for r in range(lo, hi):
        lr = learners[r]
        act = _select(choose[r], mask[r], tie[r], noise[r], draw[r], params[EPSILON], explore)
        action[r] = act
        delta[r] = 0
        if last_action[lr] >= 0:
            delta[r] = reward[r] - q_last[lr] + gamma * q[r, act]


@_JIT
def update_phase(
    weight: np.ndarray,
    tables: np.ndarray,
    learners: np.ndarray,
    params: np.ndarray,
    last_action: np.ndarray,
    trace_index: np.ndarray,
    trace_value: np.ndarray,
    delta: np.ndarray,
    parts: int,
    lo: int,
    hi: int,
) -> None:
    """The traced updates of the rows whose weight table is ``part`` modulo ``parts``, for ``part`` in
    ``lo .. hi - 1``, in row order."""
    step = params[STEP]
    for r in range(learners.shape[0]):
        lr = learners[r]
        if last_action[lr] >= 0 and lo <= tables[lr] % parts < hi:
            _add_traced(weight[tables[lr]], trace_index[lr], trace_value[lr], step * delta[r])


@_JIT
def finish_phase(
    weight: np.ndarray,
    tables: np.ndarray,
    learners: np.ndarray,
    tiles: np.ndarray,
    q: np.ndarray,
    mask: np.ndarray,
    params: np.ndarray,
    skip_matching: bool,
    last_action: np.ndarray,
    q_last: np.ndarray,
    trace_index: np.ndarray,
    trace_value: np.ndarray,
    action: np.ndarray,
    chosen: np.ndarray,
    lo: int,
    hi: int,
) -> None:
    """Q_LastAction, the traces and the pending action of rows ``lo .. hi - 1`` (lines 3, 18-25)."""
    for r in range(lo, hi):
        lr = learners[r]
        act = action[r]
        chosen[r] = tiles[r, act]
        starting = last_action[lr] < 0
        if starting:
            q_last[lr] = q[r, act]
        else:
            q_last[lr] = tile_sum(weight[tables[lr]], tiles[r, act])
        _replace_traces(
            trace_index[lr], trace_value[lr], tiles[r], mask[r], act, starting, params, skip_matching
        )
        last_action[lr] = act


@_JIT
def end_rows(
    weight: np.ndarray,
    tables: np.ndarray,
    learners: np.ndarray,
    reward: np.ndarray,
    params: np.ndarray,
    last_action: np.ndarray,
    q_last: np.ndarray,
    trace_index: np.ndarray,
    trace_value: np.ndarray,
) -> None:
    """``SarsaLambda.end_episode``: delta = r - Q_LastAction on the traced weights, then no pending action."""
    for r in range(learners.shape[0]):
        lr = learners[r]
        if last_action[lr] >= 0:
            scale = params[STEP] * (reward[r] - q_last[lr])
            _add_traced(weight[tables[lr]], trace_index[lr], trace_value[lr], scale)
    for r in range(learners.shape[0]):
        last_action[learners[r]] = -1


class SarsaLambdaNumba(SarsaLambda):
    """:class:`SarsaLambda` with ``action_values``, ``decide`` and ``end_episode`` compiled (CPU only);
    the same arguments, state and random stream."""

    kernels = "numba"

    def __init__(self, coder: TileCoding, *args: Any, **kwargs: Any) -> None:
        if coder.weight.device.type != "cpu":
            raise ValueError(f"kernels='numba' runs on the CPU only, not {coder.weight.device}; use 'torch'")
        super().__init__(coder, *args, **kwargs)
        self._shape = np.array([coder.tilings, coder.num_actions, coder.size], dtype=np.int64)
        self._params = np.zeros(5, dtype=coder.weight.numpy().dtype)
        self._params[[STEP, GAMMA, DECAY, MIN_TRACE, EPSILON]] = (
            self.step_size,
            self.gamma,
            self.gamma * self.lambda_,
            self.min_trace,
            self.epsilon,
        )
        self._skip_matching = self.gamma * self.lambda_ < self.min_trace
        self._key: tuple[int, ...] = ()
        self._tensors: tuple[torch.Tensor, ...] = ()
        self._arrays: tuple[np.ndarray, ...] = ()

    def _views(self) -> tuple[np.ndarray, ...]:
        """Numpy views of (weight, widths, tables, last_action, q_last, trace_index, trace_value), made
        again only when a tensor was replaced or the weights' storage moved (``load_state_dict`` and
        ``forget_episodes`` work in place)."""
        coder = self.coder
        weight = coder.weight
        tensors = (
            weight,
            coder.widths,
            self.tables,
            self.last_action,
            self.q_last,
            self.trace_index,
            self.trace_value,
        )
        key = (*map(id, tensors), weight.data_ptr())
        if key != self._key:
            self._key, self._tensors = key, tensors  # the tensors are kept so that their ids stay theirs
            self._arrays = tuple(t.detach().numpy() for t in tensors)
        return self._arrays

    def action_values(self, learners: torch.Tensor, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The active tiles [M, A, N] and Q [M, A] of each row's state, compiled."""
        coder = self.coder
        if obs.shape[-1] != coder.num_features:
            raise ValueError(f"expected {coder.num_features} state variables, got shape {tuple(obs.shape)}")
        weight, widths, tables = self._views()[:3]
        tiles = tile_indices(as_numpy(obs), widths, coder.tilings, coder.num_actions, coder.size)
        q = np.empty(tiles.shape[:2], dtype=np.float64)
        table_sums(weight, tables[as_numpy(learners, torch.int64)], tiles, q)
        return torch.from_numpy(tiles), torch.from_numpy(q.astype(weight.dtype))

    def decide(
        self,
        learners: torch.Tensor,
        obs: torch.Tensor,
        mask: torch.Tensor,
        reward: torch.Tensor,
        *,
        explore: bool = True,
        values: tuple[torch.Tensor, torch.Tensor] | None = None,
        choose_by: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """:meth:`SarsaLambda.decide`, compiled: the same arguments, actions and state."""
        coder = self.coder
        if obs.shape[-1] != coder.num_features:
            raise ValueError(f"expected {coder.num_features} state variables, got shape {tuple(obs.shape)}")
        weight, widths, tables, last_action, q_last, trace_index, trace_value = self._views()
        m, a = mask.shape
        tie = torch.rand(m, a, generator=self.generator).numpy()
        if self.ties == "first":  # equal scores: the first tied action wins, as on the torch path
            tie = np.zeros_like(tie)
        noise = torch.rand(m, a, generator=self.generator).numpy()
        draw = torch.rand(m, generator=self.generator).numpy()
        action = np.empty(m, dtype=np.int64)
        chosen = np.empty((m, coder.active_tiles), dtype=np.int64)
        rows, dtype = as_numpy(learners, torch.int64), coder.weight.dtype
        inputs = (as_numpy(mask, torch.bool), as_numpy(reward, dtype))
        common = (*inputs, tie, noise, draw, self._params, explore)
        state = (self._skip_matching, last_action, q_last, trace_index, trace_value, action, chosen)
        with_states = values is None
        if with_states:
            tiles_np = np.empty((m, a, coder.active_tiles), dtype=np.int64)
            q_np = np.empty((m, a), dtype=weight.dtype)
        else:
            tiles_np, q_np = as_numpy(values[0], torch.int64), as_numpy(values[1], dtype)
        choose = q_np if choose_by is None else as_numpy(choose_by)
        threads = thread_count(m, MIN_ROWS_PER_THREAD)
        states = as_numpy(obs)
        ok = decide_rows(threads, weight, widths, self._shape, tables, rows, states, with_states, tiles_np,
                         q_np, choose, *common, *state)  # fmt: skip
        if not ok:
            raise ValueError("decide: rows must name distinct learners")
        self.chosen_tiles = torch.from_numpy(chosen)
        return torch.from_numpy(action)

    def end_episode(self, learners: torch.Tensor, reward: torch.Tensor) -> None:
        """:meth:`SarsaLambda.end_episode`, compiled."""
        weight, _, tables, last_action, q_last, trace_index, trace_value = self._views()
        rows = as_numpy(learners, torch.int64)
        reward_np = as_numpy(reward, self.coder.weight.dtype)
        end_rows(weight, tables, rows, reward_np, self._params, last_action, q_last, trace_index, trace_value)
