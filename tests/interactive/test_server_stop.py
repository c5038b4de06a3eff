"""``TeachingServer.stop()`` returns promptly with pages open, as with none open.

Each page is a real WebSocket client (aiohttp, its own thread) connected with the page's origin. Before the
server closed its pages first, a stop with a page open waited out a 10 s join timeout; now it takes a few
milliseconds (docs/security.md). Serial: it asserts on wall-clock time.
"""

from __future__ import annotations

import asyncio
import threading
import time

import aiohttp
import pytest

from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession


def stop_seconds(pages: int) -> float:
    """One trial: ``pages`` pages connected and receiving, then the server stopped."""
    server = TeachingServer(TeachingSession(), port=0, max_connections=max(4, pages))
    server.start()
    ready = threading.Barrier(pages + 1)

    async def page() -> None:
        origin = f"http://127.0.0.1:{server.port}"
        async with aiohttp.ClientSession() as client:
            ws = await client.ws_connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin)
            await ws.receive(timeout=10)
            ready.wait()
            async for _ in ws:
                pass

    threads = [threading.Thread(target=asyncio.run, args=(page(),)) for _ in range(pages)]
    for t in threads:
        t.start()
    ready.wait()
    time.sleep(0.2)  # frames flowing
    t0 = time.perf_counter()
    server.stop()
    seconds = time.perf_counter() - t0
    for t in threads:
        t.join(timeout=30)
    return seconds


@pytest.mark.parametrize("pages", [0, 1, 4])
def test_stop_with_pages_open_returns_within_a_second(pages):
    assert stop_seconds(pages) < 1.0
