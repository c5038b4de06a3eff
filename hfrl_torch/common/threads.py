"""How many threads a compiled kernel splits its rows over: the whole-cycle keepaway kernels their
fields, the compiled Sarsa learner its decisions (each as numba ``prange`` regions over row ranges)."""

from __future__ import annotations

import os

import numba


def available_threads() -> int:
    """The threads ``threads=auto`` runs on: the cores this process may use (its CPU affinity, which Slurm
    and containers set), no more than ``OMP_NUM_THREADS`` where that is set (Ray sets it to a task's CPUs)
    nor than numba's pool (``NUMBA_NUM_THREADS``)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    omp = os.environ.get("OMP_NUM_THREADS", "")
    if omp.isdigit() and int(omp) > 0:
        cores = min(cores, int(omp))
    return max(1, min(cores, numba.config.NUMBA_NUM_THREADS))


def thread_count(rows: int, min_rows_per_thread: int) -> int:
    """Threads worth using on ``rows`` rows: ``numba.get_num_threads()`` (which ``threads=`` sets),
    fewer where a thread would get less than ``min_rows_per_thread`` rows (then a second thread costs
    more than it saves)."""
    if rows < 2 * min_rows_per_thread:
        return 1
    return max(1, min(numba.get_num_threads(), rows // min_rows_per_thread))


@numba.njit(cache=True, nogil=True, inline="always")
def part_range(rows: int, part: int, parts: int) -> tuple[int, int]:
    """Rows ``lo .. hi - 1`` of range ``part`` when ``rows`` rows split into ``parts`` contiguous ranges
    (inside a kernel's ``prange`` over the parts)."""
    return rows * part // parts, rows * (part + 1) // parts
