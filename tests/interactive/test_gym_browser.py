"""End to end in a real headless Chromium: ``train.py domain=gym domain.env_id=CartPole-v1 agent=dqn
trainer=interactive``. The page draws CartPole's own frames on its canvas, speaks of steps, actions and
returns (no Tetris or keepaway words), files a press under the step on screen the reaction allowance before
it, fits 390 px, and says at once that the run stops on Ctrl-C, whose summary counts the press.

Needs Debian's chromium and the ``playwright`` package; skipped, saying why, where either is missing.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from pathlib import Path

import pytest
from chromium import ARGS, CHROMIUM, needs_chromium

from hfrl_torch.feedback.log import load_feedback_log

ROOT = Path(__file__).resolve().parents[2]
playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
pytestmark = needs_chromium
OTHER_DOMAINS = re.compile(
    r"tetris|placement|\blines?\b|keeper|taker|\bball\b|column|practi[cs]e round|\bgames?\b", re.IGNORECASE
)
# the canvas: its size, and how many distinct colours a 40 x 40 grid of its pixels has (1: blank)
CANVAS = """() => {
  const c = document.getElementById("view"), g = c.getContext("2d");
  const seen = new Set();
  for (let i = 0; i < 40; i++) for (let j = 0; j < 40; j++) {
    const d = g.getImageData(Math.floor(i * c.width / 40), Math.floor(j * c.height / 40), 1, 1).data;
    seen.add(`${d[0]},${d[1]},${d[2]}`);
  }
  return { width: c.width, height: c.height, colours: seen.size };
}"""
LAYOUT = """() => {
  const e = document.documentElement;
  return { width: e.clientWidth, scroll: e.scrollWidth };
}"""


def _url(proc: subprocess.Popen, said: deque[str], timeout: float = 180) -> str:
    """The page's URL from train.py's stderr; the lines after it go on into ``said``."""
    deadline = time.time() + timeout
    assert proc.stderr is not None
    while time.time() < deadline:
        line = proc.stderr.readline()
        said.append(line)
        if "Teach the agent in your browser:" in line:
            threading.Thread(target=said.extend, args=(proc.stderr,), daemon=True).start()
            return line.split("browser:", 1)[1].strip()
        if not line and proc.poll() is not None:
            break
    raise AssertionError("train.py did not print the page's URL:\n" + "".join(said))


def test_a_gym_page_shows_the_tasks_frames_in_its_own_words_and_stops_on_ctrl_c(tmp_path) -> None:
    run_dir = tmp_path / "live"
    args = [sys.executable, str(ROOT / "train.py"), "domain=gym", "domain.env_id=CartPole-v1", "agent=dqn"]
    args += ["trainer=interactive", "trainer.port=0", "agent.boards=2", "agent.eval_episodes=2"]
    args += ["logger.backend=none", f"hydra.run.dir={run_dir}"]
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said: deque[str] = deque(maxlen=40)
    try:
        url = _url(proc, said)
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(url)
            page.wait_for_function("S.frame && !document.getElementById('good').disabled", timeout=60_000)
            page.wait_for_timeout(600)  # a few steps: the frame drawn, and one on screen 0.3 s before a press
            canvas = page.evaluate(CANVAS)
            assert (canvas["width"], canvas["height"]) == (600, 400) and canvas["colours"] > 2, canvas
            text = page.inner_text("body")
            assert not OTHER_DOMAINS.findall(text), (OTHER_DOMAINS.findall(text), text)
            assert "CartPole-v1" in page.inner_text("#help") and "steps/s" in page.inner_text("#speed-box")
            assert page.input_value("#speed") == "5"  # one step per domain.seconds_per_step (0.2 s)
            assert page.inner_text("#status").startswith("Judge each step")

            page.keyboard.press("/")
            page.wait_for_function("document.getElementById('given').textContent === '1'")
            pressed = page.inner_text("#last-press")
            filed = re.fullmatch(r"Good → action ([01]) at step (\d+) of episode (\d+)", pressed)
            assert filed, pressed
            (tmp_path / "teaching.png").write_bytes(page.screenshot())
            page.set_viewport_size({"width": 390, "height": 900})
            page.wait_for_timeout(50)
            layout = page.evaluate(LAYOUT)
            assert layout["scroll"] <= layout["width"], layout

            stopped = time.monotonic()
            proc.send_signal(signal.SIGINT)
            page.wait_for_function("/stopping/.test(document.getElementById('status').textContent)")
            said_at = time.monotonic() - stopped
            page.wait_for_selector("#summary:not([hidden])", timeout=30_000)
            summary = page.inner_text("#summary")
            assert "1 presses counted: 1 good, 0 bad" in summary and pressed.split("→ ")[1] in summary
            assert not OTHER_DOMAINS.findall(summary), (OTHER_DOMAINS.findall(summary), summary)
            (tmp_path / "page.png").write_bytes(page.screenshot())
            browser.close()
        assert proc.wait(timeout=30) == 130
    finally:
        if proc.poll() is None:
            proc.kill()
    assert said_at < 2.0
    events = [e for e in load_feedback_log(run_dir / "feedback.jsonl") if e.session.endswith("/browser")]
    assert [(e.value, e.step + 1, e.episode + 1) for e in events] == [(1.0, int(filed[2]), int(filed[3]))]
