"""End to end in a real headless Chromium: train.py trainer=interactive (Tetris, and domain=keepaway), a page,
keys pressed, events learned.

Needs Debian's chromium (``/usr/bin/chromium``, installed by ``.ci/run``) and the ``playwright`` package
(which drives it; no browser download). Skipped, saying why, where either is missing.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import pytest
import torch

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.feedback.log import load_feedback_log

if TYPE_CHECKING:
    from playwright.sync_api import Page

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
pytestmark = pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian's chromium is not installed")
ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def _url(proc: subprocess.Popen, timeout: float = 120) -> str:
    deadline = time.time() + timeout
    assert proc.stderr is not None
    while time.time() < deadline:
        line = proc.stderr.readline()
        if "Teach the agent in your browser:" in line:
            return line.split("browser:", 1)[1].strip()
        if not line and proc.poll() is not None:
            break
    raise AssertionError("train.py did not print the page's URL")


def _train(run_dir: Path, *overrides: str) -> subprocess.Popen:
    """``train.py`` with the browser trainer on a free port, its stderr readable for the page's URL."""
    args = [
        sys.executable,
        str(ROOT / "train.py"),
        *overrides,
        "logger.backend=none",
        f"hydra.run.dir={run_dir}",
    ]
    return subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


@contextlib.contextmanager
def _teach(run_dir: Path, ready: str, wait: float, *overrides: str) -> Iterator[Page]:
    """train.py with the browser trainer and a Chromium page on it once ``ready`` (a JS condition)
    holds; leaving the block closes the page (the person leaves) and the run must then finish."""
    proc = _train(run_dir, "trainer=interactive", "trainer.port=0", *overrides)
    try:
        url = _url(proc)
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page()
            page.goto(url)
            page.wait_for_function(ready, timeout=60_000)
            yield page
            browser.close()
        assert proc.wait(timeout=wait) == 0
    finally:
        if proc.poll() is None:
            proc.kill()


def _press(page: Page, keys: list[str]) -> None:
    for key in keys:
        page.keyboard.press(key)
        page.wait_for_timeout(300)


def test_person_presses_keys_and_the_learner_gets_them(tmp_path):
    run_dir = tmp_path / "live"
    overrides = ["trainer.actions_per_s=4", "agent.iterations=3", "agent.population=10"]
    overrides += ["agent.games_per_candidate=1", "agent.eval_games=3", "agent.watch_pieces=60"]
    ready = "document.getElementById('score').textContent !== '-'"
    with _teach(run_dir, ready, 240, *overrides) as page:
        _press(page, ["/", "/", "z"])
        page.click("#good")
        page.wait_for_timeout(300)
        assert page.inner_text("#given") == "4"
        (tmp_path / "page.png").write_bytes(page.screenshot())
    # the person left: training went on from the game alone

    events = load_feedback_log(run_dir / "feedback.jsonl")
    assert [e.value for e in events] == [1.0, 1.0, -1.0, 1.0]
    assert {e.source for e in events} == {"human:browser"}
    # credit: each event names the placement on screen when it was given, in the game being watched
    assert all(e.episode == 0 and 0 <= e.step < 60 for e in events)
    assert [e.step for e in events] == sorted(e.step for e in events)
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert rows[0]["feedback/given"] == 4 and rows[0]["feedback/learned_total"] == 4
    assert [r["feedback/trainer_present"] for r in rows[1:]] == [0.0, 0.0]  # page closed: no teacher
    state = load_checkpoint(run_dir)["state"]
    assert torch.count_nonzero(torch.as_tensor(state["human"]["weight"])) > 0  # H^ learned from the person


def test_person_teaches_the_keepers_in_the_browser(tmp_path):
    run_dir = tmp_path / "live"
    overrides = ["domain=keepaway", "trainer.actions_per_s=20", "trainer.wait_for_page_s=60"]
    overrides += ["agent.hours=0.02", "agent.table_bits=12"]
    ready = "document.getElementById('score').textContent.endsWith(' s')"
    with _teach(run_dir, ready, 120, *overrides) as page:
        assert "keepers" in page.inner_text("#help")
        assert page.inner_text("#speed-unit").startswith("decisions")
        _press(page, ["/", "z"])
        assert page.inner_text("#given") == "2"
        (tmp_path / "page.png").write_bytes(page.screenshot())
    # the person left: the keepers went on from the environment alone

    events = load_feedback_log(run_dir / "feedback.jsonl")
    assert [e.value for e in events] == [1.0, -1.0]
    assert {e.source for e in events} == {"human:browser"}
    assert all(0.0 <= e.time <= 80.0 and e.episode >= 0 for e in events)  # on the field's simulated clock
    human = load_checkpoint(run_dir)["state"]["human"]
    assert int(human["feedback"].sum()) == 2 and human["trainer"] == {"given": 2, "positive": 1}
    assert torch.count_nonzero(human["human_weight"]) > 0  # H^ learned from the person
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    assert rows[-1]["feedback/events_per_learner"] == 2.0
