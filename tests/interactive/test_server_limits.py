"""What the page's server withstands: a flood of idle sockets under a 1,024 file-handle limit, half-sent
requests, a page that stops reading, and odd static paths."""

from __future__ import annotations

import asyncio
import json
import resource
import socket
import subprocess
import sys
import textwrap
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import aiohttp
import pytest

from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def served():
    session = TeachingSession(actions_per_s=5.0)
    server = TeachingServer(session, port=0, max_messages_per_s=200, idle_timeout_s=1.0)
    server.start()
    yield session, server
    server.stop()


def _status(url: str) -> int:
    try:
        return urllib.request.urlopen(url, timeout=10).status
    except urllib.error.HTTPError as e:
        return e.code


def test_long_and_odd_static_paths_are_a_plain_404(served):
    _, server = served
    base = f"http://127.0.0.1:{server.port}/static/"
    assert _status(base + "app.js") == 200
    for name in ["a" * 300, "b" * 5000, "..%2Fserver.py", "nothing.js", "index.html"]:
        assert _status(base + name) == 404, name
    assert server.errors == 0


def test_a_half_sent_request_is_closed_after_the_idle_timeout_and_an_open_page_is_not(served):
    _, server = served

    async def page_survives() -> bool:
        origin = f"http://127.0.0.1:{server.port}"
        async with aiohttp.ClientSession() as client, client.ws_connect(f"{origin}/ws", origin=origin) as ws:
            await asyncio.sleep(2.5)  # well past the idle timeout
            await ws.send_str('{"type": "speed", "actions_per_s": 2}')
            while True:
                m = json.loads((await ws.receive(timeout=10)).data)
                if m["type"] == "ack":
                    return True

    with socket.create_connection(("127.0.0.1", server.port), timeout=10) as s:
        s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1")  # never finished
        started = time.monotonic()
        assert s.recv(100) == b""  # closed by the server
        assert time.monotonic() - started < 5
    assert asyncio.run(page_survives())


async def _acks_while_a_page_stalls(port: int, n: int) -> list[float]:
    """Seconds from each settings message to its acknowledgement, with a second page that never reads."""
    origin = f"http://127.0.0.1:{port}"
    waits = []
    async with aiohttp.ClientSession() as client, client.ws_connect(f"{origin}/ws", origin=origin) as ws:
        stalled = socket.create_connection(("127.0.0.1", port), timeout=10)
        stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        handshake = [
            "GET /ws HTTP/1.1",
            f"Host: 127.0.0.1:{port}",
            f"Origin: {origin}",
            "Upgrade: websocket",
            "Connection: Upgrade",
            "Sec-WebSocket-Version: 13",
            "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
        ]
        stalled.sendall(("\r\n".join(handshake) + "\r\n\r\n").encode())
        await asyncio.sleep(1.0)  # the big frames fill the stalled page's buffers
        for i in range(n):
            sent = time.monotonic()
            await ws.send_str(json.dumps({"type": "speed", "actions_per_s": 1 + i % 5}))
            while True:
                m = json.loads((await ws.receive(timeout=10)).data)
                if m["type"] == "ack":
                    waits.append(time.monotonic() - sent)
                    break
        stalled.close()
    return waits


def test_a_page_that_never_reads_does_not_delay_the_teachers_acknowledgements(served):
    session, server = served
    for i in range(3000):  # a long run's curve: every settings message carries it (about 60 kB)
        session.add_point(i, i / 7, 1.0)
    stop = threading.Event()

    def publish() -> None:  # large frames, as fast as a page may get them
        while not stop.is_set():
            session.publish({"type": "status", "text": "x" * 200_000})
            time.sleep(0.02)

    threading.Thread(target=publish, daemon=True).start()
    try:
        waits = asyncio.run(_acks_while_a_page_stalls(server.port, 30))
    finally:
        stop.set()
    assert len(waits) == 30 and max(waits) < 1.0, max(waits)


_FLOODED = textwrap.dedent(
    """
    import resource, sys, time
    from pathlib import Path
    from hfrl_torch.interactive.server import TeachingServer
    from hfrl_torch.interactive.session import TeachingSession

    resource.setrlimit(resource.RLIMIT_NOFILE, (1024, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
    server = TeachingServer(TeachingSession(), port=0)
    server.start()
    print(server.port, flush=True)
    metrics, done = Path(sys.argv[1]), Path(sys.argv[2])
    started = time.monotonic()
    while not done.exists() and time.monotonic() - started < 120:  # what the run does: write its files
        with metrics.open("a") as f:
            f.write("1\\n")
        time.sleep(0.02)
    server.stop()
    print("alive", flush=True)
    """
)


def test_two_thousand_idle_sockets_under_a_1024_handle_limit_leave_the_run_and_its_page_working(tmp_path):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 2200:
        pytest.skip(f"this test opens 2,000 sockets; the hard file-handle limit here is {hard}")
    resource.setrlimit(
        resource.RLIMIT_NOFILE, (4096 if hard == resource.RLIM_INFINITY else min(hard, 4096), hard)
    )
    run = subprocess.Popen(
        [sys.executable, "-c", _FLOODED, str(tmp_path / "metrics.jsonl"), str(tmp_path / "done")],
        stdout=subprocess.PIPE,
        text=True,
        cwd=ROOT,
    )
    sockets: list[socket.socket] = []
    try:
        assert run.stdout is not None
        port = int(run.stdout.readline())

        async def teach() -> int:
            origin = f"http://127.0.0.1:{port}"
            acks = 0
            async with (
                aiohttp.ClientSession() as client,
                client.ws_connect(f"{origin}/ws", origin=origin) as ws,
            ):
                for _ in range(2000):  # the flood, while the page is open (a loaded machine's server
                    # may let its accept backlog fill: the kernel then retries the handshake for seconds)
                    try:
                        sockets.append(socket.create_connection(("127.0.0.1", port), timeout=30))
                    except OSError:
                        break
                for i in range(5):
                    await ws.send_str(json.dumps({"type": "speed", "actions_per_s": 1 + i}))
                    while json.loads((await ws.receive(timeout=30)).data)["type"] != "ack":
                        pass
                    acks += 1
            return acks

        assert asyncio.run(teach()) == 5
        assert len(sockets) == 2000
        (tmp_path / "done").touch()
        assert run.stdout.readline().strip() == "alive"
        assert run.wait(timeout=60) == 0
    finally:
        for s in sockets:
            s.close()
        if run.poll() is None:
            run.kill()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert len((tmp_path / "metrics.jsonl").read_text().splitlines()) > 10
