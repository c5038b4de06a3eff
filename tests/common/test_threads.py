"""The thread settings a run applies, and how many threads a compiled kernel splits its rows over."""

from __future__ import annotations

import os

import numba
import torch
from omegaconf import OmegaConf

from hfrl_torch.common.threads import available_threads, thread_count
from hfrl_torch.experiment.factories import set_threads


def test_thread_count_splits_only_where_each_thread_gets_enough_rows() -> None:
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        assert thread_count(10_000, 64) == 1
        if numba.config.NUMBA_NUM_THREADS >= 2:
            numba.set_num_threads(2)
            assert thread_count(127, 64) == 1  # a second thread would get under 64 rows
            assert thread_count(128, 64) == 2
            assert thread_count(10_000, 64) == 2  # never more than numba's threads
    finally:
        numba.set_num_threads(before)


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


def test_auto_threads_are_the_cores_this_process_may_use(monkeypatch) -> None:
    before = torch.get_num_threads(), numba.get_num_threads()
    cores = min(len(os.sched_getaffinity(0)), numba.config.NUMBA_NUM_THREADS)
    try:
        monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
        assert available_threads() == cores
        assert set_threads(OmegaConf.create({"threads": "auto"})) == cores == numba.get_num_threads()
        monkeypatch.setenv("OMP_NUM_THREADS", "1")  # a Ray task of one CPU
        assert available_threads() == 1
        monkeypatch.setenv("OMP_NUM_THREADS", "junk")  # not a count: ignored
        assert available_threads() == cores
    finally:
        torch.set_num_threads(before[0])
        numba.set_num_threads(before[1])
