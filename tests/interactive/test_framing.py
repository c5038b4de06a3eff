"""In a real headless Chromium: a page of another site that frames the teaching page gets no teaching page
(the frame is refused), so it cannot connect, become the teacher or be clicked through a decoy.

Needs Debian's chromium and the ``playwright`` package; skipped, saying why, where either is missing.
"""

from __future__ import annotations

import time

import pytest
from chromium import ARGS, CHROMIUM, decoy_site, needs_chromium

from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession

playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
pytestmark = needs_chromium


def test_a_page_of_another_site_cannot_frame_the_teaching_page():
    session = TeachingSession(actions_per_s=5.0)
    server = TeachingServer(session, port=0)
    server.start()
    site, decoy = decoy_site([server.url] * 4)
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page()
            page.goto(decoy)
            time.sleep(3.0)  # the page, had it loaded in a frame, connects within a second
            framed = [f for f in page.frames if f != page.main_frame]
            assert len(framed) == 4
            assert session.clients == 0  # no frame ran the page, so none connected or teaches
            assert all("Teach the agent" not in f.content() for f in framed)
            own = browser.new_page()  # the person's own tab still connects and teaches
            own.goto(server.url)
            own.wait_for_function("() => document.body.innerText.length > 0")
            deadline = time.monotonic() + 10
            while session.clients == 0 and time.monotonic() < deadline:
                time.sleep(0.1)
            assert session.clients == 1
            browser.close()
    finally:
        site.shutdown()
        server.stop()
