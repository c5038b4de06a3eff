"""The thread settings a run applies, and the row splitter the compiled kernels run on."""

from __future__ import annotations

import threading

import numba
import torch
from omegaconf import OmegaConf

from hfrl_torch.common.threads import run_parts
from hfrl_torch.experiment.factories import set_threads


def test_run_parts_covers_the_rows_in_order_and_runs_the_first_range_here() -> None:
    here = threading.get_ident()
    seen: list[tuple[int, int, bool]] = []

    def kernel(tag: str, lo: int, hi: int) -> tuple[str, int, int]:
        seen.append((lo, hi, threading.get_ident() == here))
        return tag, lo, hi

    assert run_parts(kernel, 1, 10, "a") == [("a", 0, 10)]
    out = run_parts(kernel, 3, 10, "b")
    assert out == [("b", 0, 3), ("b", 3, 6), ("b", 6, 10)]
    assert (0, 3, True) in seen  # the caller's own range: one hand-off fewer
    assert not any(mine for lo, _, mine in seen if lo > 0)


def test_threads_sets_the_kernels_threads_and_keeps_torch_at_one() -> None:
    before = torch.get_num_threads(), numba.get_num_threads()
    try:
        n = set_threads(OmegaConf.create({"threads": 2}))
        assert n == min(2, numba.config.NUMBA_NUM_THREADS)
        assert numba.get_num_threads() == n
        assert torch.get_num_threads() == 1
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])
