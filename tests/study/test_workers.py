"""Workers are real train.py runs (tiny Tetris budgets, no page): one starts, serves its port, is stopped
(SIGTERM), resumes its own run directory with resume= and ends by itself, which moves its participant to
the questionnaire; and a worker dies when the study server is killed (PR_SET_PDEATHSIG)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from hfrl_torch.study import layout
from hfrl_torch.study.config import StudyConfig
from hfrl_torch.study.manager import Study
from hfrl_torch.study.workers import REPO, accepts, alive, fresh_command

TINY = [
    "domain=tetris",
    "agent=cem",
    "fusion=linear",
    "agent.population=10",
    "agent.games_per_candidate=1",
    "agent.eval_games=1",
    "agent.watch_pieces=5",
    "logger.backend=none",
    "threads=1",
    "trainer.wait_for_page_s=0",
]
START_S = 180.0  # imports and numba on a loaded 2-core machine: 10-40 s


def _until(done: Callable[[], bool], timeout: float, poll: Callable[[], None] = lambda: None) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, "timed out"
        poll()
        time.sleep(0.02)


def _iterations(run: Path) -> list[int]:
    path = run / layout.METRICS
    if not path.exists():
        return []
    return [json.loads(line)["iteration"] for line in path.read_text().splitlines() if line.strip()]


def test_start_stop_resume_finish(raw: dict[str, Any], tmp_path: Path) -> None:
    raw.update(
        calibration={"trials": 0, "optional": True},
        common=[],
        conditions=[{"label": "tetris", "overrides": [*TINY, "agent.iterations=300"]}],
    )
    study = Study.open(StudyConfig.from_node(raw), tmp_path / "s", credits={"tetris": "previous_step"})
    try:
        p = study.join(simulated=True)
        for step in ("consent", "instructions", "practice"):
            study.advance(p.code, step, "agree" if step == "consent" else "next", {})
        assert study.state(p.code)["step"] == "teaching"
        run = study.directory / p.run_dir
        _until(lambda: (run / layout.CHECKPOINT).exists(), START_S, study.poll)
        study.stop(p.code)  # SIGTERM: the run ends its chunk and saves
        _until(lambda: study.overview()[0]["worker"] == "none", 60, study.poll)
        stopped_at = _iterations(run)
        assert stopped_at == list(range(1, len(stopped_at) + 1)) and len(stopped_at) < 300
        assert study.state(p.code)["step"] == "teaching"
        study.resume(p.code)
        _until(lambda: study.teaching_endpoint(p.code) is not None, START_S, study.poll)
        _until(lambda: study.state(p.code)["step"] == "questionnaire", START_S, study.poll)
        assert study.state(p.code)["ended"] == "finished"
        assert _iterations(run) == list(range(1, 301))  # the same run went on: each iteration once
        assert study.state(p.code)["summary"]["reason"] == "finished"
        assert [d.name for d in run.parent.iterdir() if d.name.startswith("run")] == ["run"]
        log = (run.parent / layout.WORKER_LOG).read_text()
        assert f"resume={run}" in log and "trainer=interactive" in log
        exits = [e["by"] for e in layout.read_events(study.directory) if e["event"] == "worker_exit"]
        assert exits == ["study", "itself"]
    finally:
        study.close(timeout=10)


def test_worker_dies_with_its_server(tmp_path: Path) -> None:
    """The study server is killed with SIGKILL: its worker gets SIGTERM (pdeathsig), saves and ends."""
    run = tmp_path / "run"
    command = fresh_command(
        sys.executable, REPO / "train.py", [*TINY, "agent.iterations=100000"], run, 0, "t" * 16, 1
    )
    script = textwrap.dedent(
        f"""
        import sys, time
        from pathlib import Path
        from hfrl_torch.study.workers import Worker
        log, pid = Path({str(tmp_path / "worker.log")!r}), Path({str(tmp_path / "pid")!r})
        w = Worker({command!r}, 0, "t" * 16, log, pid)
        w.start()
        time.sleep(3600)
        """
    )
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    server = subprocess.Popen([sys.executable, "-c", script], env=env, start_new_session=True)
    try:
        _until(lambda: (run / layout.CHECKPOINT).exists(), START_S)
        pid = int((tmp_path / "pid").read_text())
        assert alive(pid)
        server.kill()
        server.wait()
        _until(lambda: not alive(pid), 60)
        log = (tmp_path / "worker.log").read_text()
        assert "Interrupted" in log and "resume=" in log  # a graceful stop: saved, with the way to go on
    finally:
        if server.poll() is None:
            server.kill()
        pid_path = tmp_path / "pid"
        if pid_path.exists() and alive(int(pid_path.read_text())):
            os.kill(int(pid_path.read_text()), signal.SIGKILL)


@pytest.mark.parametrize("port", [1])
def test_accepts_refused(port: int) -> None:
    assert not accepts(port)
