"""How long ``TeachingServer.stop()`` takes with pages open, next to the same stop with no page open.

Each page is a real WebSocket client (aiohttp, its own thread) connected with the page's origin. Before the
server closed its pages first, a stop with a page open waited out a 10 s join timeout. Prints one JSON line
per number of pages: the stop's wall seconds over ``--trials`` trials.

    python benchmarks/teaching_server_stop.py [--pages 0 1 4] [--trials 5]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import statistics
import threading
import time

import aiohttp

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pages", type=int, nargs="+", default=[0, 1, 4])
    parser.add_argument("--trials", type=int, default=5)
    args = parser.parse_args()
    for pages in args.pages:
        runs = [stop_seconds(pages) for _ in range(args.trials)]
        print(
            json.dumps(
                {
                    "pages": pages,
                    "stop_s_median": round(statistics.median(runs), 4),
                    "stop_s_max": round(max(runs), 4),
                    "trials": args.trials,
                }
            )
        )


if __name__ == "__main__":
    main()
