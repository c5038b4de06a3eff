"""Fixtures shared by the test modules."""

from __future__ import annotations

from collections.abc import Iterator

import numba
import pytest
import torch
from hypothesis import settings

from hfrl_torch.experiment.cli import compose_train as _compose_train

settings.register_profile("deterministic", derandomize=True, database=None, print_blob=True)
settings.load_profile("deterministic")

# Tests that assert on wall-clock latency (a stop within 2 s, a press flashed in time) or drive a browser:
# `make test` runs them alone after the rest, which runs on both cores (pytest-xdist).
SERIAL_DIRS = {"interactive"}
SERIAL_FILES = {"test_events.py"}
PARALLEL_FILES = {
    "test_press_journal.py",
    "test_kill_while_paused.py",
    "test_keepaway_effort.py",
}  # in interactive/, no latency


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the latency and browser tests ``serial``."""
    for item in items:
        if item.path.name in PARALLEL_FILES:
            continue
        if SERIAL_DIRS & set(item.path.parts) or item.path.name in SERIAL_FILES:
            item.add_marker(pytest.mark.serial)


@pytest.fixture(scope="module")
def one_thread() -> Iterator[None]:
    """One torch and one numba thread: the machine is shared, and numba's idle threads slow torch."""
    torch_threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    yield
    torch.set_num_threads(torch_threads)
    numba.set_num_threads(numba_threads)


def _run_learner(run_dir, *overrides: str, checkpoint=None, stop_after: int | None = None, prepare=None):
    """Run the learner of ``overrides`` (``train.py``'s loop, no Hydra run directory) in ``run_dir``;
    returns the learner and its result. ``stop_after``: stop as Ctrl-C would after that many points (the
    result is then None); ``prepare``: called with the learner before it learns."""
    from hfrl_torch.experiment.registry import learner_for
    from hfrl_torch.experiment.run import Callback, Interrupt, RunFiles, learn

    cfg = _compose_train("logger.backend=none", *overrides)
    run_dir.mkdir(parents=True, exist_ok=True)
    learner = learner_for(cfg.agent.name, cfg.domain.name)(cfg, run_dir, checkpoint)
    if prepare is not None:
        prepare(learner)
    interrupt = Interrupt()

    class StopAfter(Callback):
        def on_point(self, learner, point) -> None:
            if stop_after is not None and len(learner.history) >= stop_after:
                interrupt.requested = True

    try:
        final = learn(learner, RunFiles(run_dir, cfg), [StopAfter()], interrupt)
    except KeyboardInterrupt:
        final = None
    return learner, final


@pytest.fixture
def compose_train():
    """``compose_train(*overrides)``: the checked ``train`` config of ``overrides``."""
    return _compose_train


@pytest.fixture
def run_learner():
    """``run_learner(run_dir, *overrides, ...)``: train.py's loop on ``overrides`` in ``run_dir``."""
    return _run_learner
