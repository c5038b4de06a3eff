"""A real ``study.py`` for the tests: started in its own process group on a free port, its address read from
what it prints, stopped (SIGTERM) or killed with all its workers (SIGKILL to the group)."""

from __future__ import annotations

import contextlib
import os
import re
import resource
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
URL = re.compile(r"https?://127\.0\.0\.1:(\d+)/")
# Tetris CE on 6x8 boards, long enough not to end during a test; the page's default pace (1.5 placements/s)
TETRIS = ["domain=tetris", "agent=cem", "agent.iterations=50", "agent.population=8"]
TETRIS += ["agent.games_per_candidate=1", "agent.eval_games=1", "agent.watch_pieces=200"]
TETRIS += ["domain.width=6", "domain.height=8", "trainer.actions_per_s=4"]
COMMON = ["trainer.wait_for_page_s=120", "threads=1", "logger.backend=none"]


def quoted(values: list[str]) -> str:
    """A Hydra list override's value: ``['a=b','c=d']``."""
    return "[" + ",".join(f"'{v}'" for v in values) + "]"


def study_args(directory: Path, participants: int, conditions: dict[str, list[str]]) -> list[str]:
    """``study.py`` with a tiny study in ``directory``: the pilot's texts, ``conditions`` (label: train.py
    overrides), no calibration, 5 s of practice, ``COMMON`` for every run."""
    listed = ",".join("{label:" + k + ",overrides:" + quoted(v) + "}" for k, v in conditions.items())
    return [
        sys.executable,
        str(ROOT / "study.py"),
        "study=pilot",
        "study.name=test",
        f"study.dir={directory}",
        "study.port=0",
        f"study.max_participants={participants}",
        "study.practice_s=5",
        "study.calibration.trials=0",
        f"study.common={quoted(COMMON)}",
        f"study.conditions=[{listed}]",
    ]


class StudyProc:
    """``study.py`` running: :attr:`base` is its address, :attr:`log` what it printed."""

    def __init__(self, args: list[str], log: Path, nofile: int | None = None, timeout: float = 60.0) -> None:
        self.log = log
        preexec: Callable[[], None] | None = None
        if nofile is not None:
            hard = resource.getrlimit(resource.RLIMIT_NOFILE)[1]

            def preexec() -> None:
                resource.setrlimit(resource.RLIMIT_NOFILE, (nofile, hard))

        with log.open("w") as out:
            self.proc = subprocess.Popen(
                args,
                cwd=ROOT,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,  # its own process group: the workers are in it
                preexec_fn=preexec,
            )
        self.base = self._address(timeout)

    def _address(self, timeout: float) -> str:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for line in self.log.read_text().splitlines()[::-1]:
                m = URL.search(line)
                if m and "admin" not in line and "token" not in line:
                    return f"http://127.0.0.1:{m.group(1)}"
            if self.proc.poll() is not None:
                break
            time.sleep(0.2)
        self.kill()
        raise AssertionError(f"study.py did not print its address:\n{self.log.read_text()[-3000:]}")

    def kill(self, workers: list[Path] = ()) -> None:
        """SIGKILL to every worker of ``workers`` (their pid files: each worker has its own session) and to
        the study's process group, at once: nothing of the study gets to save."""
        pids = []
        for path in workers:
            with contextlib.suppress(OSError, ValueError):
                pids.append(int(path.read_text().strip()))
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=30)

    def stop(self, timeout: float = 60.0) -> int:
        """SIGTERM (the study stops its workers and saves), SIGKILL to the group after ``timeout``."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.kill()
        with contextlib.suppress(ProcessLookupError):  # anything left in its group
            os.killpg(self.proc.pid, signal.SIGKILL)
        return self.proc.returncode
