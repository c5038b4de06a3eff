"""Debian's Chromium for the browser tests: where it is, the flags it runs with here, the skip without it, and
a decoy site of another origin that frames a page (the clickjacking tests)."""

from __future__ import annotations

import http.server
import shutil
import threading
from collections.abc import Iterable
from pathlib import Path

import pytest

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
# headless as root, and nothing reaching out of this machine's closed network
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
needs_chromium = pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian's chromium is not installed")


def decoy_site(urls: Iterable[str]) -> tuple[http.server.ThreadingHTTPServer, str]:
    """Serve, on another port (another origin), a page with a decoy button that frames each of ``urls``;
    returns the server (``shutdown()`` it) and the page's address."""
    frames = "".join(f'<iframe src="{url}" width="400" height="300"></iframe>' for url in urls)
    body = f"<html><body><button>Win a prize</button>{frames}</body></html>".encode()

    class Decoy(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    site = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Decoy)
    threading.Thread(target=site.serve_forever, daemon=True).start()
    return site, f"http://127.0.0.1:{site.server_address[1]}/"
