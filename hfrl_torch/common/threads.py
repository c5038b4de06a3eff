"""How many threads a compiled kernel splits its rows over: the whole-cycle keepaway kernels their
fields, the compiled Sarsa learner its decisions (each as numba ``prange`` regions over row ranges)."""

from __future__ import annotations

import numba


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
