"""The browser trainer's server: the page, the WebSocket, validation, rate limit, token, pacing."""

from __future__ import annotations

import asyncio
import json
import time
import urllib.error
import urllib.request

import aiohttp
import pytest

from hfrl_torch.interactive.server import TeachingServer, is_loopback
from hfrl_torch.interactive.session import TeachingSession


@pytest.fixture
def served():
    session = TeachingSession(actions_per_s=5.0)
    server = TeachingServer(session, port=0, max_messages_per_s=50)
    server.start()
    yield session, server
    server.stop()


async def _exchange(url: str, sends: list[str], wait_for: int) -> list[dict]:
    got: list[dict] = []
    async with aiohttp.ClientSession() as client, client.ws_connect(url) as ws:
        for raw in sends:
            await ws.send_str(raw)
        deadline = time.monotonic() + 10
        while len(got) < wait_for and time.monotonic() < deadline:
            msg = await ws.receive(timeout=10)
            got.append(json.loads(msg.data))
    return got


def test_page_and_static_files_are_served(served):
    _, server = served
    html = urllib.request.urlopen(server.url, timeout=10).read().decode()
    assert "Teach the agent" in html and "static/app.js" in html
    js = urllib.request.urlopen(server.url.rstrip("/") + "/static/app.js", timeout=10).read().decode()
    assert "new WebSocket" in js


def test_feedback_reaches_the_queue_and_bad_messages_are_rejected(served):
    session, server = served
    ws_url = f"ws://127.0.0.1:{server.port}/ws"
    sends = [
        '{"type": "feedback", "value": 1}',
        "garbage",
        '{"type": "feedback", "value": 7}',
        '{"type": "speed", "actions_per_s": 7}',
        '{"type": "feedback", "value": -1}',
    ]
    got = asyncio.run(_exchange(ws_url, sends, wait_for=9))
    kinds = [m["type"] for m in got]
    assert kinds[0] == "config" and got[0]["keys"]["good"] == "/"
    errors = [m["message"] for m in got if m["type"] == "error"]
    assert any("not valid JSON" in e for e in errors) and any("value=7 is invalid" in e for e in errors)
    events = session.queue.drain()
    assert [e.value for e in events] == [1.0, -1.0]
    assert {e.source for e in events} == {"human:browser"}
    assert session.actions_per_s == 7.0 and session.rejected == 2 and session.received == 3


def test_frames_published_by_the_loop_reach_the_page(served):
    session, server = served
    session.publish({"type": "status", "text": "hello from the loop"})
    got = asyncio.run(_exchange(f"ws://127.0.0.1:{server.port}/ws", [], wait_for=3))
    assert {"type": "status", "text": "hello from the loop"} in got


def test_flood_is_rate_limited_and_training_side_survives():
    session = TeachingSession()
    with TeachingServer(session, port=0, max_messages_per_s=5) as server:
        sends = ['{"type": "feedback", "value": 1}'] * 40
        got = asyncio.run(_exchange(f"ws://127.0.0.1:{server.port}/ws", sends, wait_for=42))
    limited = [m for m in got if m["type"] == "error" and "too many messages" in m["message"]]
    assert limited and len(session.queue.drain()) <= 12


def test_token_is_required_off_loopback_and_checked():
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and not is_loopback("0.0.0.0")
    assert TeachingServer(TeachingSession(), host="0.0.0.0").token  # generated
    session = TeachingSession()
    with TeachingServer(session, port=0, token="s3cret-token") as server:
        assert server.url.endswith("?token=s3cret-token")
        assert urllib.request.urlopen(server.url, timeout=10).status == 200
        with pytest.raises(urllib.error.HTTPError) as info:
            urllib.request.urlopen(server.url.split("?")[0], timeout=10)
        assert info.value.code == 403


def test_wait_turn_paces_actions_and_pause_blocks_only_while_someone_watches():
    clock = [100.0]
    slept: list[float] = []

    def sleep(s: float) -> None:
        slept.append(s)
        clock[0] += s

    session = TeachingSession(actions_per_s=4.0, clock=lambda: clock[0], sleep=sleep)
    assert session.wait_turn() == 100.0
    assert session.wait_turn() == 100.25 and slept == [0.25]
    session.paused = True  # paused, but no page is open: the agent goes on
    assert session.wait_turn() == 100.5


def test_curve_points_reach_the_page_even_when_frames_follow_at_once(served):
    session, server = served
    session.add_point(1, 12.5)
    session.publish({"type": "status", "text": "next game"})
    got = asyncio.run(_exchange(f"ws://127.0.0.1:{server.port}/ws", [], wait_for=4))
    assert {"type": "curve", "curve": [[1.0, 12.5]]} in got
