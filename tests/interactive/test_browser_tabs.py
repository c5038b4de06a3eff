"""In a real headless Chromium, against the page's server alone: reloading the teaching tab keeps it the
teacher (a watching tab does not take over), and a run whose process is gone is said to be gone, not to be
waiting. Needs Debian's chromium and the ``playwright`` package; skipped, saying why, where either is missing.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest
from chromium import ARGS, CHROMIUM, needs_chromium

from hfrl_torch.interactive.live import LiveTeaching
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.trainers.queue_trainer import QueueTrainer

playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
pytestmark = needs_chromium
ROOT = Path(__file__).resolve().parents[2]
STATUS = "document.getElementById('status').textContent"


def _says(page, text: str, timeout_ms: int = 10_000) -> None:
    page.wait_for_function(f"{STATUS}.includes({text!r})", timeout=timeout_ms)


def test_reloading_the_teaching_tab_keeps_it_teaching_and_the_other_tab_watching():
    session = TeachingSession(actions_per_s=5.0)
    server = TeachingServer(session, port=0, max_connections=3)
    server.start()
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            context = browser.new_context()
            teacher, other = context.new_page(), context.new_page()
            teacher.goto(server.url)
            teacher.wait_for_function("S.connected && S.role === 'teach'")
            other.goto(server.url)
            _says(other, "Watching only")
            for _ in range(2):
                teacher.reload()
                teacher.wait_for_function("S.connected")
                assert teacher.evaluate("S.role") == "teach", teacher.inner_text("#status")
                time.sleep(0.5)
                assert other.evaluate("S.role") == "watch" and "Watching only" in other.inner_text("#status")
            teacher.close()  # closed for good: the other tab teaches once the place is no longer kept
            other.wait_for_function("S.role === 'teach'", timeout=(session.reconnect_s + 5) * 1000)
            browser.close()
    finally:
        server.stop()


_RUN = textwrap.dedent(
    """
    import time
    from hfrl_torch.interactive.server import TeachingServer
    from hfrl_torch.interactive.session import TeachingSession

    server = TeachingServer(TeachingSession(), port=0)
    server.start()
    print(server.url, flush=True)
    time.sleep(600)
    """
)


def test_a_killed_run_is_said_to_have_stopped_within_about_two_seconds():
    run = subprocess.Popen([sys.executable, "-c", _RUN], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert run.stdout is not None
        url = run.stdout.readline().strip()
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page()
            page.goto(url)
            page.wait_for_function("S.connected")
            run.kill()
            killed = time.monotonic()
            _says(page, "Connection to the run lost")
            assert "If the run is still going" in page.inner_text("#status")
            _says(page, "The run does not answer: it may have stopped")
            assert time.monotonic() - killed < 3.0
            browser.close()
    finally:
        run.kill()


def test_the_summary_counts_the_presses_the_run_refused_and_those_the_page_kept_back():
    session = TeachingSession(actions_per_s=5.0)
    server = TeachingServer(session, port=0, view="keepaway")
    server.start()
    teaching = LiveTeaching(server, session, QueueTrainer(session.queue))
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page()
            page.goto(server.url)
            page.wait_for_function("S.connected && S.role === 'teach'")
            session.publish({"type": "status", "text": "a new episode"})
            session.shown(0.0, 0, -1, "")  # on screen, but no move made yet: the run refuses presses
            time.sleep(0.6)  # the frame on screen 0.3 s before the press is that one
            page.keyboard.press("/")
            page.wait_for_function(
                "document.getElementById('last-press').textContent.includes('not counted')"
            )
            page.keyboard.press("h")  # away: the page keeps presses back itself
            page.wait_for_function("!S.here")
            page.keyboard.press("/")
            page.keyboard.press("z")
            teaching.stop("stopped")
            page.wait_for_selector("#summary", state="visible", timeout=10_000)
            said = page.inner_text("#summary-presses")
            assert "0 presses counted" in said and "3 more were not counted" in said, said
            assert "1 refused by the run" in said and "2 kept back by this page" in said, said
            assert "2 you said you are away" in said, said
            browser.close()
    finally:
        teaching.stop("stopped")
