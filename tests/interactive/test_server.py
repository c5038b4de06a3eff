"""The browser trainer's server: the page, the WebSocket, validation, rate limit, token, pacing, and who may
connect (Host, Origin, token, connection cap), aggregated rejection logs and a prompt stop."""

from __future__ import annotations

import asyncio
import json
import logging
import socket
import threading
import time
import urllib.error
import urllib.request

import aiohttp
import pytest

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment.checks import check_interactive
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.interactive.live import LiveTeaching
from hfrl_torch.interactive.messages import Finish
from hfrl_torch.interactive.server import TeachingServer, is_loopback, split_authority
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.trainers.queue_trainer import QueueTrainer

FEEDBACK = '{"type": "feedback", "value": 1}'


@pytest.fixture
def served():
    session = TeachingSession(actions_per_s=5.0)
    server = TeachingServer(session, port=0, max_messages_per_s=50)
    server.start()
    yield session, server
    server.stop()


def _origin(server: TeachingServer) -> str:
    return f"http://127.0.0.1:{server.port}"


def _ws_url(server: TeachingServer) -> str:
    query = f"?token={server.token}" if server.token else ""
    return f"ws://127.0.0.1:{server.port}/ws{query}"


async def _exchange(url: str, sends: list[str], wait_for: int, origin: str | None = None) -> list[dict]:
    if origin is None:
        origin = "http://" + url.split("/")[2]
    got: list[dict] = []
    async with aiohttp.ClientSession() as client, client.ws_connect(url, origin=origin) as ws:
        for raw in sends:
            await ws.send_str(raw)
        deadline = time.monotonic() + 10
        while len(got) < wait_for and time.monotonic() < deadline:
            msg = await ws.receive(timeout=10)
            got.append(json.loads(msg.data))
    return got


def _replies(got: list[dict]) -> list[str]:
    return [m["type"] for m in got if m["type"] in ("ack", "error")]


def _http(port: int, path: str, host: str | None, origin: str | None = None, upgrade: bool = False) -> int:
    """The status of a raw HTTP/1.1 GET (any Host header, or none)."""
    lines = [f"GET {path} HTTP/1.1"]
    if host is not None:
        lines.append(f"Host: {host}")
    if origin is not None:
        lines.append(f"Origin: {origin}")
    if upgrade:
        lines += ["Upgrade: websocket", "Connection: Upgrade", "Sec-WebSocket-Version: 13"]
        lines.append("Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==")
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1"))
        return int(s.recv(4096).split(b" ", 2)[1])


def test_page_and_static_files_are_served(served):
    _, server = served
    html = urllib.request.urlopen(server.url, timeout=10).read().decode()
    assert "Teach the agent" in html and "static/app.js" in html
    js = urllib.request.urlopen(server.url.rstrip("/") + "/static/app.js", timeout=10).read().decode()
    assert "new WebSocket" in js


def test_feedback_reaches_the_queue_and_bad_messages_are_rejected(served):
    session, server = served
    sends = [
        FEEDBACK,
        "garbage",
        '{"type": "feedback", "value": 7}',
        '{"type": "speed", "actions_per_s": 7}',
        '{"type": "feedback", "value": -1}',
    ]
    got = asyncio.run(_exchange(_ws_url(server), sends, wait_for=10))
    kinds = [m["type"] for m in got]
    assert kinds[:3] == ["config", "settings", "role"] and got[0]["keys"]["good"] == "/"
    assert got[2]["role"] == "teach"
    errors = [m["message"] for m in got if m["type"] == "error"]
    assert any("not valid JSON" in e for e in errors) and any("value=7 is invalid" in e for e in errors)
    events = session.queue.drain()
    assert [e.value for e in events] == [1.0, -1.0]
    assert {e.source for e in events} == {"human:browser"}
    assert session.actions_per_s == 7.0 and session.rejected == 2 and session.received == 3


def test_frames_published_by_the_loop_reach_the_page(served):
    session, server = served
    session.publish({"type": "status", "text": "hello from the loop"})
    got = asyncio.run(_exchange(_ws_url(server), [], wait_for=4))
    assert {"type": "status", "text": "hello from the loop"} in got


def test_flood_is_rate_limited_and_training_side_survives():
    session = TeachingSession()
    with TeachingServer(session, port=0, max_messages_per_s=5) as server:
        got = asyncio.run(_exchange(_ws_url(server), [FEEDBACK] * 40, wait_for=43))
    limited = [m for m in got if m["type"] == "error" and "too many messages" in m["message"]]
    assert limited and len(session.queue.drain()) <= 12


def test_the_rate_limit_is_the_sessions_not_each_connections():
    session = TeachingSession()
    with TeachingServer(session, port=0, max_messages_per_s=5, clock=lambda: 100.0) as server:
        first = asyncio.run(_exchange(_ws_url(server), [FEEDBACK] * 12, wait_for=16))
        again = asyncio.run(_exchange(_ws_url(server), [FEEDBACK] * 5, wait_for=9))  # a new connection
    assert _replies(first) == ["ack"] * 10 + ["error"] * 2  # a burst of 10, and the clock stands still
    assert _replies(again) == ["error"] * 5
    assert len(session.queue.drain()) == 10


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
        host = f"127.0.0.1:{server.port}"
        for bad in ("/?token=%C3%A9t%C3%A9", "/?token=%ff%fe", "/?token=%", "/ws?token=%00"):
            assert _http(server.port, bad, host) == 403
        raw = "/?token=\u00e9t\u00e9".encode().decode("latin-1")  # not even a valid request line
        assert _http(server.port, raw, host) == 400
        assert _http(server.port, "/?token=s3cret-token", host) == 200
    assert server.errors == 0 and server.rejections.total == 6


@pytest.mark.parametrize(
    "origin",
    [
        "http://evil.example",
        "null",
        "file://",
        "https://127.0.0.1:{port}",
        "http://127.0.0.1:1",
        None,
        "http://127.0.0.1:{port}/path",
        "http://user@127.0.0.1:{port}",
        "http://localhost:{port}",
    ],
)
def test_websockets_from_other_origins_are_refused(served, origin):
    session, server = served
    status = _http(
        server.port,
        "/ws",
        f"127.0.0.1:{server.port}",
        None if origin is None else origin.format(port=server.port),
        upgrade=True,
    )
    assert status == 403 and session.clients == 0
    assert server.rejections.counts["bad Origin"] == 1


def test_the_page_own_origin_connects_also_as_localhost(served):
    _, server = served
    assert _http(server.port, "/ws", f"127.0.0.1:{server.port}", _origin(server), upgrade=True) == 101
    local = f"localhost:{server.port}"
    assert _http(server.port, "/ws", local, f"http://{local}", upgrade=True) == 101


@pytest.mark.parametrize(
    "host",
    ["evil.example:{port}", "127.0.0.1:1", "127.0.0.1", "[::1]:{port}", "", "127.0.0.1:{port}:1", None],
)
def test_requests_naming_another_host_are_refused(served, host):
    """DNS rebinding: a page of evil.example whose name now points at 127.0.0.1 sends Host: evil.example."""
    session, server = served
    h = None if host is None else host.format(port=server.port)
    for path, origin, upgrade in [
        ("/", None, False),
        ("/static/app.js", None, False),
        ("/ws", f"http://{h}", True),
    ]:
        assert _http(server.port, path, h, origin, upgrade) == 400
    assert session.clients == 0


def test_a_wildcard_address_takes_ip_literals_and_its_own_names_with_the_token():
    with TeachingServer(TeachingSession(), host="0.0.0.0", port=0, allowed_hosts=["teacher.lan"]) as server:
        token = f"/?token={server.token}"
        for host in ("127.0.0.1", "teacher.lan", socket.gethostname()):
            assert _http(server.port, token, f"{host}:{server.port}") == 200
        assert _http(server.port, token, f"evil.example:{server.port}") == 400
        assert _http(server.port, "/", f"127.0.0.1:{server.port}") == 403
        ws = f"/ws?token={server.token}"
        assert (
            _http(server.port, ws, f"teacher.lan:{server.port}", f"http://teacher.lan:{server.port}", True)
            == 101
        )
        assert _http(server.port, ws, f"teacher.lan:{server.port}", "http://evil.example", True) == 403


def test_split_authority():
    assert split_authority("LocalHost:8765") == ("localhost", 8765)
    assert split_authority("[::1]:80") == ("::1", 80) and split_authority("example.org") == (
        "example.org",
        80,
    )
    for bad in ("", "a:b", "a:99999", "::1:80", "[::1", "[zz]:1", "a/b:1", "a@b:1", "\u00e9:1", "a:+1"):
        assert split_authority(bad) is None, bad


async def _connect(server: TeachingServer, client: aiohttp.ClientSession):
    ws = await client.ws_connect(_ws_url(server), origin=_origin(server))
    first = [json.loads((await ws.receive(timeout=10)).data) for _ in range(3)]
    return ws, first[2]["role"]


async def _reply(ws) -> dict:
    while True:
        m = json.loads((await ws.receive(timeout=10)).data)
        if m["type"] in ("ack", "error", "role"):
            return m


def test_one_page_teaches_the_others_watch_and_the_cap_holds():
    session = TeachingSession()
    with TeachingServer(session, port=0, max_connections=3) as server:

        async def scenario() -> None:
            async with aiohttp.ClientSession() as client:
                (t, rt), (w1, r1), (w2, r2) = [await _connect(server, client) for _ in range(3)]
                assert (rt, r1, r2) == ("teach", "watch", "watch")
                with pytest.raises(aiohttp.WSServerHandshakeError) as info:
                    await client.ws_connect(_ws_url(server), origin=_origin(server))
                assert info.value.status == 503
                await w1.send_str(FEEDBACK)
                await w2.send_str('{"type": "pause", "paused": true}')
                assert "only watches" in (await _reply(w1))["message"]
                assert "only watches" in (await _reply(w2))["message"]
                await t.send_str(FEEDBACK)
                assert (await _reply(t))["type"] == "ack"
                assert (server.teachers, server.watchers, session.clients) == (1, 2, 3)
                await t.close()  # the teacher leaves: the oldest watcher teaches
                assert (await _reply(w1)) == {
                    "type": "role",
                    "role": "teach",
                    "text": "connected: you are teaching",
                }
                await w1.send_str(FEEDBACK)
                assert (await _reply(w1))["type"] == "ack"
                await w2.send_str(FEEDBACK)
                assert (await _reply(w2))["type"] == "error"
                await w1.close()
                await w2.close()

        asyncio.run(scenario())
    assert len(session.queue.drain()) == 2 and not session.paused
    assert server.rejections.counts["too many pages"] == 0  # counted, then logged and cleared at stop


def test_a_reloading_teacher_keeps_its_place_and_a_tab_that_does_not_come_back_hands_it_on():
    session = TeachingSession()
    with TeachingServer(session, port=0, max_connections=3, hold_s=1.0) as server:

        async def page(client: aiohttp.ClientSession, tab: str):
            url = f"ws://127.0.0.1:{server.port}/ws?tab={tab}"
            ws = await client.ws_connect(url, origin=_origin(server))
            first = [json.loads((await ws.receive(timeout=10)).data) for _ in range(3)]
            return ws, first[2]["role"]

        async def scenario() -> None:
            async with aiohttp.ClientSession() as client:
                (t, rt), (w, rw) = await page(client, "tabA"), await page(client, "tabB")
                assert (rt, rw) == ("teach", "watch")
                await t.close()  # the teaching tab reloads
                await asyncio.sleep(0.2)
                (t, rt) = await page(client, "tabA")  # ... and comes back as the teacher
                assert rt == "teach" and (server.teachers, server.watchers) == (1, 1)
                await w.send_str(FEEDBACK)
                assert "only watches" in (await _reply(w))["message"]
                await t.close()  # closed for good: after hold_s the watching tab teaches
                await asyncio.sleep(0.3)
                (x, rx) = await page(client, "tabC")  # a page opening meanwhile does not take the place
                assert rx == "watch"
                started = time.monotonic()
                assert (await _reply(w))["role"] == "teach"
                assert 0.3 < time.monotonic() - started + 0.3 < 2.0
                await w.send_str(FEEDBACK)
                assert (await _reply(w))["type"] == "ack"
                await w.close()
                await x.close()

        asyncio.run(scenario())


def test_rejections_are_logged_in_aggregate(caplog):
    session = TeachingSession()
    with caplog.at_level(logging.WARNING, logger="hfrl_torch.interactive"):
        with TeachingServer(session, port=0, max_messages_per_s=1000, rejection_log_s=0.2) as server:
            asyncio.run(_exchange(_ws_url(server), ["garbage"] * 2000, wait_for=2003))
            time.sleep(0.5)  # a quiet interval logs nothing more
            lines = server.rejections.lines
        records = [r for r in caplog.records if r.name == "hfrl_torch.interactive"]
    assert session.rejected == 2000
    assert 1 <= lines == len(records) <= 12  # one per 0.2 s of the flood at most, not one per message
    total = sum(int(r.getMessage().split()[1]) for r in records)
    assert total == 2000 and all("invalid (e.g. message is not valid JSON" in r.getMessage() for r in records)


def test_stop_closes_open_pages_first_and_returns_promptly():
    session = TeachingSession()
    server = TeachingServer(session, port=0)
    server.start()
    closed: list[int | None] = []
    connected = threading.Event()

    async def page() -> None:
        async with aiohttp.ClientSession() as client:
            ws, _ = await _connect(server, client)
            connected.set()
            async for _ in ws:
                pass
            closed.append(ws.close_code)

    thread = threading.Thread(target=asyncio.run, args=(page(),))
    thread.start()
    assert connected.wait(10)
    server.stop()
    thread.join(10)
    assert closed == [1001] and not server._thread.is_alive() and session.clients == 0  # type: ignore[union-attr]


def test_a_press_acknowledged_just_before_stop_is_in_the_log(tmp_path):
    log = FeedbackLog(tmp_path / "feedback.jsonl", "live")
    session = TeachingSession()
    server = TeachingServer(session, port=0)
    server.start()
    teaching = LiveTeaching(server, session, QueueTrainer(session.queue, log=log))

    async def press() -> list[dict]:
        async with aiohttp.ClientSession() as client:
            ws, _ = await _connect(server, client)
            acks = []
            for value in (1, -1, 1):
                await ws.send_str(json.dumps({"type": "feedback", "value": value}))
                acks.append(await _reply(ws))
            return acks

    acks = asyncio.run(press())
    assert [a["type"] for a in acks] == ["ack"] * 3
    assert teaching.stop() == 3 and teaching.stop() == 0
    log.close()
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert [e.value for e in events] == [1.0, -1.0, 1.0] and {e.source for e in events} == {"human:browser"}
    assert [e.seq for e in events] == [0, 1, 2]


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
    got = asyncio.run(_exchange(_ws_url(server), [], wait_for=5))
    assert {"type": "curve", "curve": [[1.0, 12.5, 0.0]]} in got


def test_connection_limits_from_the_config_are_checked():
    def cfg(*overrides: str):
        return compose_config("train", "trainer=interactive", *overrides)

    check_interactive(cfg())
    check_interactive(cfg("trainer.max_teachers=2", "trainer.max_connections=3"))
    with pytest.raises(
        ConfigError, match=r"trainer\.max_connections=0 is invalid: must be an integer in 1\.\.64"
    ):
        check_interactive(cfg("trainer.max_connections=0"))
    with pytest.raises(ConfigError, match=r"trainer\.max_teachers=5 is invalid: must be at most"):
        check_interactive(cfg("trainer.max_teachers=5"))


def test_stop_tells_every_page_the_end_before_closing_it_within_a_second():
    session = TeachingSession()
    server = TeachingServer(session, port=0, max_connections=2)
    server.start()
    got: list[list[dict]] = [[], []]
    closed: list[int | None] = []
    connected = threading.Barrier(3)

    async def page(i: int) -> None:
        async with aiohttp.ClientSession() as client:
            ws = await client.ws_connect(_ws_url(server), origin=_origin(server))
            connected.wait()
            async for msg in ws:
                got[i].append(json.loads(msg.data))
            closed.append(ws.close_code)

    threads = [threading.Thread(target=asyncio.run, args=(page(i),)) for i in range(2)]
    for t in threads:
        t.start()
    connected.wait(timeout=10)
    time.sleep(0.2)
    t0 = time.monotonic()
    LiveTeaching(server, session, QueueTrainer(session.queue)).stop("stopped", {"run_dir": "/runs/r"})
    took = time.monotonic() - t0
    for t in threads:
        t.join(10)
    assert took < 1.0 and closed == [1001, 1001]
    for messages in got:  # the teaching page and the watching one
        end = messages[-1]
        assert end["type"] == "end" and end["reason"] == "stopped" and end["run_dir"] == "/runs/r"


def test_a_stop_or_finish_reaches_the_page_at_once_and_later_presses_are_not_taken():
    session = TeachingSession()
    with TeachingServer(session, port=0) as server:

        async def scenario() -> list[dict]:
            async with aiohttp.ClientSession() as client:
                ws, _ = await _connect(server, client)
                await ws.send_str(json.dumps({"type": "finish"}))
                replies = [await _reply(ws)]
                session.request_stop()  # then Ctrl-C, from the loop's signal handler
                t0 = time.monotonic()
                while True:
                    m = json.loads((await ws.receive(timeout=10)).data)
                    if m["type"] == "settings" and m["ending"] == "stopping":
                        break
                replies.append({"seconds": time.monotonic() - t0})
                await ws.send_str(json.dumps({"type": "feedback", "value": 1, "id": 41}))
                replies.append(await _reply(ws))
                return replies

        finish, told, press = asyncio.run(scenario())
    assert finish["type"] == "ack" and finish["message"] == "finish"
    assert told["seconds"] < 0.5
    assert press == {
        "type": "error",
        "message": "not taken: the run is stopping; this press was not saved",
        "id": 41,
    }
    assert session.taken == 0 and len(session.queue) == 0


def test_nothing_is_lost_or_duplicated_when_a_page_drops_and_reconnects(tmp_path):
    log = FeedbackLog(tmp_path / "feedback.jsonl", "live")
    session = TeachingSession()
    server = TeachingServer(session, port=0, max_messages_per_s=1000)
    server.start()
    teaching = LiveTeaching(server, session, QueueTrainer(session.queue, log=log))
    sent = [1 if i % 3 else -1 for i in range(40)]

    async def scenario() -> tuple[list[int], int, list[int]]:
        async with aiohttp.ClientSession() as client:
            ws, _ = await _connect(server, client)
            for i, value in enumerate(sent[:30]):  # 30 presses in flight, then the connection drops
                await ws.send_str(json.dumps({"type": "feedback", "value": value, "id": i}))
            first = []
            while len(first) < 10:
                m = await _reply(ws)
                first.append(m["id"])
            ws._response.connection.transport.abort()  # no close handshake: a lost connection
        async with aiohttp.ClientSession() as client:
            ws = await client.ws_connect(_ws_url(server), origin=_origin(server))
            hello = [json.loads((await ws.receive(timeout=10)).data) for _ in range(3)]
            count = next(m for m in hello if m["type"] == "settings")["given"]
            second = []
            for i, value in enumerate(sent[30:], start=30):
                await ws.send_str(json.dumps({"type": "feedback", "value": value, "id": i}))
                second.append((await _reply(ws))["id"])
            return first, count, second

    first, count, second = asyncio.run(scenario())
    teaching.stop("stopped")
    log.close()
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert first == list(range(10)) and second == list(range(30, 40))
    # the reconnected page is told how many the run took (what it counts from then on): each of them is
    # logged once, in order, and so is every press acknowledged after
    assert 10 <= count <= 30 and session.taken == count + 10 and len(events) == count + 10
    assert [e.value for e in events] == [float(v) for v in sent[:count] + sent[30:]]
    assert len({e.id for e in events}) == len(events)


def test_the_end_names_why_the_run_ended_and_how_to_continue_it(tmp_path, monkeypatch):
    session = TeachingSession()
    teaching = LiveTeaching(TeachingServer(session, port=0), session, QueueTrainer(session.queue))
    ended: list[tuple[str, dict]] = []
    monkeypatch.setattr(teaching, "stop", lambda reason, saved: ended.append((reason, saved)) or 0)
    teaching.end(True, tmp_path, "agent.iterations", 50)  # the budget is spent
    teaching.end(False, tmp_path, "agent.iterations", 50)  # Ctrl-C
    try:
        raise RuntimeError("the loop failed")
    except RuntimeError:  # as in the run loop's ``finally`` with an exception on its way out
        teaching.end(False, tmp_path, "agent.iterations", 50)
    session.apply(Finish())
    teaching.end(False, tmp_path, "agent.iterations", 50)
    assert [reason for reason, _ in ended] == ["finished", "stopped", "failed", "finished_by_you"]
    assert ended[0][1]["resume"] == f"python train.py resume={tmp_path} agent.iterations=50"
    assert {saved["resume"] for _, saved in ended[1:]} == {f"python train.py resume={tmp_path}"}
    assert ended[0][1]["checkpoint"] is None  # none written yet: the page says so
    assert ended[0][1]["feedback_log"] == str(tmp_path / "feedback.jsonl")
    with pytest.raises(ValueError, match="reason='done' is invalid; allowed: finished, finished_by_you"):
        LiveTeaching(TeachingServer(session, port=0), session, QueueTrainer(session.queue)).stop("done")


def _headers(port: int, path: str, host: str) -> tuple[int, dict[str, str]]:
    """The status and headers of a raw HTTP/1.1 GET."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(f"GET {path} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n".encode("latin-1"))
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
    head = data.split(b"\r\n\r\n", 1)[0].decode("latin-1").split("\r\n")
    fields = dict(line.split(": ", 1) for line in head[1:] if ": " in line)
    return int(head[0].split(" ", 2)[1]), {k.lower(): v for k, v in fields.items()}


def test_no_other_site_may_frame_the_page(served):
    """Clickjacking: a page elsewhere framed the trainer (its WebSocket passed the Origin check: the frame is
    served from here) and a decoy over it clicked Finish and save. Every response forbids framing, the
    refusals included, and keeps the token in the URL out of Referer headers."""
    _, server = served
    host = f"127.0.0.1:{server.port}"
    for path, host_header, status in [
        ("/", host, 200),
        ("/static/app.js", host, 200),
        ("/no/such/page", host, 404),
        ("/", "evil.example", 400),
    ]:
        got, headers = _headers(server.port, path, host_header)
        assert got == status
        assert headers["x-frame-options"] == "DENY"
        assert headers["content-security-policy"] == "frame-ancestors 'none'"
        assert headers["referrer-policy"] == "no-referrer" and headers["x-content-type-options"] == "nosniff"
