"""Compiled kernels that release the GIL, run over ranges of rows on a few Python threads: the
whole-cycle keepaway kernels split their fields, the compiled Sarsa learner its decisions."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numba

_POOL: ThreadPoolExecutor | None = None


def thread_count(rows: int, min_rows_per_thread: int) -> int:
    """Threads worth using on ``rows`` rows: ``numba.get_num_threads()`` (which ``threads=`` sets),
    fewer where a thread would get less than ``min_rows_per_thread`` rows (then a second thread costs
    more than it saves)."""
    if rows < 2 * min_rows_per_thread:
        return 1
    return max(1, min(numba.get_num_threads(), rows // min_rows_per_thread))


def run_split(
    kernel: Callable[..., object], rows: int, *args: object, min_rows_per_thread: int = 64
) -> list[object]:
    """Run ``kernel(*args, lo, hi)`` over contiguous row ranges, one per thread, and return the results
    in range order."""
    return run_parts(kernel, thread_count(rows, min_rows_per_thread), rows, *args)


def run_parts(kernel: Callable[..., object], threads: int, rows: int, *args: object) -> list[object]:
    """``kernel(*args, lo, hi)`` on ``threads`` contiguous ranges of ``rows`` rows: the first in this thread,
    the others on the pool (one call, in this thread, when ``threads`` is 1)."""
    global _POOL
    parts = max(1, threads)
    ranges = list(itertools.pairwise(rows * t // parts for t in range(parts + 1)))
    if parts > 1 and (_POOL is None or _POOL._max_workers < parts - 1):
        _POOL = ThreadPoolExecutor(max_workers=parts - 1)
    futures = [_POOL.submit(kernel, *args, lo, hi) for lo, hi in ranges[1:]]  # none when parts is 1
    first = kernel(*args, *ranges[0])
    return [first, *(f.result() for f in futures)]
