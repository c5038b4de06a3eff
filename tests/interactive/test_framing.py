"""In a real headless Chromium: a page of another site that frames the teaching page gets no teaching page
(the frame is refused), so it cannot connect, become the teacher or be clicked through a decoy.

Needs Debian's chromium and the ``playwright`` package; skipped, saying why, where either is missing.
"""

from __future__ import annotations

import http.server
import threading
import time

import pytest
from chromium import ARGS, CHROMIUM, needs_chromium

from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession

playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
pytestmark = needs_chromium


def _decoy_site(trainer_url: str) -> tuple[http.server.ThreadingHTTPServer, str]:
    """Another site (another port is another origin) whose page frames the trainer four times."""
    frames = "".join(f'<iframe src="{trainer_url}" width="400" height="300"></iframe>' for _ in range(4))
    body = f"<html><body><button>Win a prize</button>{frames}</body></html>".encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    site = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=site.serve_forever, daemon=True).start()
    return site, f"http://127.0.0.1:{site.server_address[1]}/"


def test_a_page_of_another_site_cannot_frame_the_teaching_page():
    session = TeachingSession(actions_per_s=5.0)
    server = TeachingServer(session, port=0)
    server.start()
    site, decoy = _decoy_site(server.url)
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
