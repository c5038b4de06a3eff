"""The study's web server: the participant's API from join to done, isolation (a code opens its participant
alone, unknown codes 404, the condition is neither chosen nor shown), the researcher's token, the framing
headers on every answer, stale steps (409), bounded bodies, and the teaching proxy relaying a real
TeachingServer's acknowledgements."""

from __future__ import annotations

import asyncio
import gc
import http.client
import io
import json
import threading
import time
import zipfile
from collections.abc import Callable

import aiohttp
import pytest
from study_web import FAKE_TRAIN, LABELS, study_config, wait_for

from hfrl_torch.interactive.http_guard import SECURITY_HEADERS
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.study.manager import Study
from hfrl_torch.study.server import MAX_BODY_BYTES, OVER, WAIT, StudyServer


@pytest.fixture
def served(tmp_path):
    study = Study.open(study_config(tmp_path), tmp_path / "study", train_script=FAKE_TRAIN)
    server = StudyServer(study, port=0, max_requests_per_s=200, max_joins_per_s=200, max_misses_per_s=500)
    server.start()
    yield study, server
    server.stop()
    study.close(timeout=5)


def request(
    server: StudyServer,
    method: str,
    path: str,
    body: object = None,
    headers: dict[str, str] | None = None,
    raw: bytes | None = None,
) -> tuple[int, dict[str, str], bytes]:
    """``(status, headers, body)`` of one HTTP request to ``server`` (a JSON body, or ``raw`` bytes)."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    data = raw if raw is not None else (None if body is None else json.dumps(body).encode())
    conn.request(method, path, body=data, headers={"Content-Type": "application/json", **(headers or {})})
    r = conn.getresponse()
    out = r.status, dict(r.getheaders()), r.read()
    conn.close()
    return out


def api(server: StudyServer, method: str, path: str, body: object = None) -> tuple[int, dict]:
    status, _, data = request(server, method, path, body)
    return status, json.loads(data)


def join(server: StudyServer, body: object = None) -> str:
    status, reply = api(server, "POST", "/api/join", {"simulated": True} if body is None else body)
    assert status == 200, reply
    assert set(reply) == {"code"}
    return reply["code"]


def step(server: StudyServer, code: str, at: str, action: str = "next", data: dict | None = None) -> dict:
    status, state = api(
        server, "POST", f"/p/{code}/api/step", {"step": at, "action": action, "data": data or {}}
    )
    assert status == 200, state
    return state


def to_teaching(server: StudyServer, code: str) -> dict:
    step(server, code, "consent", "agree")
    step(server, code, "instructions")
    step(server, code, "practice")
    return step(server, code, "calibration", data={"delays_s": [0.31, 0.42]})


def named_condition(text: str) -> bool:
    return "condition" in text or any(label in text for label in LABELS)


def test_a_participant_walks_every_step_and_no_answer_names_the_condition(served):
    study, server = served
    code = join(server)
    answers: list[bytes] = []
    for path in ("/", f"/p/{code}/", f"/p/{code}/static/study.js", f"/p/{code}/teach/"):
        status, _, body = request(server, "GET", path)
        assert status == 200, path
    status, _, body = request(server, "GET", f"/p/{code}/api/state")
    answers.append(body)
    state = json.loads(body)
    assert state["step"] == "consent" and state["study"]["title"] == "Teach an agent"
    assert state["study"]["questionnaire"][0]["points"] == 5
    for at, action, data in (
        ("consent", "agree", {}),
        ("instructions", "next", {}),
        ("practice", "next", {}),
        ("calibration", "next", {"delays_s": [0.3, 0.5]}),
    ):
        status, _, body = request(
            server, "POST", f"/p/{code}/api/step", {"step": at, "action": action, "data": data}
        )
        assert status == 200, body
        answers.append(body)
    assert json.loads(answers[-1])["step"] == "teaching"
    assert study.get(code).calibration["delays_s"] == [0.3, 0.5]
    (study.directory / "participants" / code / "finish").touch()  # the fake run ends by itself
    wait_for(lambda: api(server, "GET", f"/p/{code}/api/state")[1]["step"] == "questionnaire")
    status, _, body = request(
        server,
        "POST",
        f"/p/{code}/api/step",
        {"step": "questionnaire", "action": "next", "data": {"answers": {"effort": 4, "comments": "ok"}}},
    )
    answers.append(body)
    assert status == 200 and json.loads(body)["step"] == "done"
    assert study.get(code).answers == {"effort": 4, "comments": "ok"}
    assert not any(named_condition(a.decode()) for a in answers)
    assert all(
        set(json.loads(a)) <= {"step", "study", "teaching", "stopped", "ended", "summary"} for a in answers
    )


def test_a_stale_step_is_409_with_the_current_state_and_changes_nothing(served):
    study, server = served
    code = join(server)
    step(server, code, "consent", "agree")
    status, state = api(
        server, "POST", f"/p/{code}/api/step", {"step": "consent", "action": "agree", "data": {}}
    )
    assert status == 409 and state["step"] == "instructions"  # a reload that sends its step again
    assert not named_condition(json.dumps(state))
    status, reply = api(server, "POST", f"/p/{code}/api/step", {"step": "instructions", "action": "agree"})
    assert status == 400 and "allowed: next" in reply["error"]
    assert study.get(code).step == "instructions"


def test_a_code_opens_its_own_participant_alone_and_unknown_codes_are_404(served):
    study, server = served
    a, b = join(server), join(server)
    step(server, a, "consent", "agree")
    assert api(server, "GET", f"/p/{a}/api/state")[1]["step"] == "instructions"
    assert api(server, "GET", f"/p/{b}/api/state")[1]["step"] == "consent"
    for bad in ("ZZZZZZZZZZZZ", a[:-1], "x" * 300, "..", "%2e%2e"):
        for path in (f"/p/{bad}/", f"/p/{bad}/api/state", f"/p/{bad}/teach/", f"/p/{bad}/static/study.js"):
            status, _, _ = request(server, "GET", path)
            assert status == 404, path
        status, _, _ = request(server, "POST", f"/p/{bad}/api/step", {"step": "consent", "action": "agree"})
        assert status == 404
    assert (
        api(server, "GET", f"/p/{a.lower()}/api/state")[1]["step"] == "instructions"
    )  # codes are case-blind
    assert study.get(b).step == "consent"


def test_join_takes_no_say_in_the_condition(tmp_path):
    """Extra fields asking for a condition are ignored: the design gives the same conditions as without."""
    got = []
    for run, body in (("plain", {"simulated": False}), ("asking", None)):
        study = Study.open(study_config(tmp_path / run), tmp_path / run / "study", train_script=FAKE_TRAIN)
        with StudyServer(study, port=0, max_joins_per_s=200) as server:
            for _ in range(6):
                asking = {"simulated": False, "condition": LABELS[2], "label": LABELS[2], "index": 5}
                join(server, body or asking)
        got.append([p["condition"] for p in study.overview()])
        study.close()
    assert got[0] == got[1]
    assert sorted(got[0]) == sorted(LABELS * 2)  # two blocks, each condition once per block


def test_join_is_refused_when_the_study_takes_codes_only_or_is_full(tmp_path):
    study = Study.open(
        study_config(tmp_path, enrollment="codes", codes=2, max_participants=2), tmp_path / "study"
    )
    with StudyServer(study, port=0) as server:
        status, reply = api(server, "POST", "/api/join", {"simulated": False})
        assert status == 403 and "codes" in reply["error"]
        code = study.premade_codes[0]
        assert api(server, "GET", f"/p/{code}/api/state")[1]["step"] == "consent"
        status, _, body = request(server, "GET", "/admin/data.zip", headers=bearer(study))
        names = zipfile.ZipFile(io.BytesIO(body)).namelist()
    assert status == 200 and "study.json" in names and f"participants/{code}/participant.json" in names
    assert not any(n.endswith(("researcher_token", "codes.txt")) for n in names)
    study.close()
    full = Study.open(study_config(tmp_path / "full", max_participants=1), tmp_path / "full" / "study")
    with StudyServer(full, port=0) as server:
        join(server)
        status, reply = api(server, "POST", "/api/join", {"simulated": False})
    assert status == 403 and "full" in reply["error"]
    full.close()


def bearer(study: Study) -> dict[str, str]:
    return {"Authorization": f"Bearer {study.researcher_token}"}


def test_the_researchers_pages_need_the_token(served):
    study, server = served
    code = join(server)
    routes = [
        ("GET", "/admin"),
        ("GET", "/admin/api/participants"),
        ("GET", "/admin/data.zip"),
        ("POST", f"/admin/api/participants/{code}/stop"),
    ]
    wrong = [{}, {"Authorization": "Bearer nope"}, {"Authorization": "Bearer " + "é" * 8}]
    for method, path in routes:
        for headers in wrong:
            assert request(server, method, path, headers=headers)[0] == 403, (path, headers)
        assert request(server, method, path + "?token=" + study.researcher_token[:-1])[0] == 403
    assert not study.get(code).stopped
    status, _, body = request(server, "GET", "/admin/api/participants", headers=bearer(study))
    rows = json.loads(body)
    assert status == 200 and rows[0]["code"] == code and rows[0]["condition"] in LABELS
    assert request(server, "GET", "/admin?token=" + study.researcher_token)[0] == 200
    assert request(server, "POST", f"/admin/api/participants/{code}/stop", headers=bearer(study))[0] == 200
    assert study.get(code).stopped and api(server, "GET", f"/p/{code}/api/state")[1]["stopped"] is True
    assert request(server, "POST", f"/admin/api/participants/{code}/resume", headers=bearer(study))[0] == 200
    assert not study.get(code).stopped
    status, headers, body = request(server, "GET", "/admin/data.zip", headers=bearer(study))
    names = zipfile.ZipFile(io.BytesIO(body)).namelist()
    assert status == 200 and headers["Content-Type"] == "application/zip"
    assert "events.jsonl" in names and "researcher_token" not in names
    assert study.researcher_token.encode() not in body


def test_every_answer_carries_the_framing_headers_refusals_included(served):
    _, server = served
    code = join(server)
    cases = [
        ("GET", "/", None, {}, 200),
        ("GET", "/static/study.css", None, {}, 200),
        ("GET", "/static/nope.js", None, {}, 404),
        ("GET", f"/p/{code}/", None, {}, 200),
        ("GET", f"/p/{code}", None, {}, 302),
        ("GET", f"/p/{code}/teach/static/app.js", None, {}, 200),
        ("GET", f"/p/{code}/teach/static/{'a' * 300}", None, {}, 404),
        ("GET", f"/p/{code}/api/state", None, {}, 200),
        ("POST", f"/p/{code}/api/step", {"step": "practice", "action": "next"}, {}, 409),
        ("POST", f"/p/{code}/api/step", [1, 2], {}, 400),
        ("GET", "/p/NOPE/", None, {}, 404),
        ("GET", "/admin", None, {}, 403),
        ("GET", "/", None, {"Host": "evil.example"}, 400),
        ("GET", f"/p/{code}/teach/ws", None, {"Origin": "http://evil.example"}, 403),
        ("GET", f"/p/{code}/teach/ws", None, {}, 403),
        ("PUT", "/api/join", None, {}, 405),
        ("GET", "/" + "x" * 3000, None, {}, 404),
    ]
    for method, path, body, headers, expected in cases:
        status, got, _ = request(server, method, path, body, headers)
        assert status == expected, (method, path, status)
        for name, value in SECURITY_HEADERS.items():
            assert got.get(name) == value, (path, name)
    assert server.errors == 0


def test_bodies_are_bounded_and_checked(served):
    study, server = served
    code = join(server)
    big = b'{"simulated": false, "pad": "' + b"x" * MAX_BODY_BYTES + b'"}'
    assert request(server, "POST", "/api/join", raw=big)[0] == 413
    for raw in (b"[" * 50 + b"]" * 50, b'{"simulated": 1' + b"0" * 50 + b"}", b"NaN", b"\xff\xfe", b"", b"{"):
        assert request(server, "POST", "/api/join", raw=raw)[0] == 400, raw
    assert api(server, "POST", "/api/join", {"simulated": "yes"})[0] == 400
    step(server, code, "consent", "agree")
    step(server, code, "instructions")
    step(server, code, "practice")
    for data in ({"delays_s": [5.0]}, {"delays_s": "fast"}, {"delays_s": [0.3], "condition": "x"}):
        status, reply = api(
            server, "POST", f"/p/{code}/api/step", {"step": "calibration", "action": "next", "data": data}
        )
        assert status == 400 and reply["error"], data
    assert study.get(code).step == "calibration"
    assert server.errors == 0


def test_each_participant_is_rate_limited_on_their_own(tmp_path):
    study = Study.open(study_config(tmp_path), tmp_path / "study", train_script=FAKE_TRAIN)
    with StudyServer(study, port=0, max_requests_per_s=5, max_joins_per_s=50) as server:
        a, b = join(server), join(server)
        statuses = [request(server, "GET", f"/p/{a}/api/state")[0] for _ in range(30)]
        assert 429 in statuses and statuses[0] == 200
        assert request(server, "GET", f"/p/{b}/api/state")[0] == 200  # the other is not held up
        guesses = [request(server, "GET", f"/p/ABCDEFGHJK{i:02d}/")[0] for i in range(40)]
        assert guesses[0] == 404 and guesses.count(429) >= 15  # codes cannot be guessed quickly
    study.close()


async def _teach(
    url: str, origin: str, sends: list[str], done: Callable[[list[dict]], bool] = lambda got: False
) -> tuple[list[dict], int | None, str]:
    """Open the teaching WebSocket at ``url``, send ``sends`` and read until ``done(messages)`` or the close;
    returns the messages, the close code and its reason."""
    got: list[dict] = []
    async with aiohttp.ClientSession() as client, client.ws_connect(url, origin=origin) as ws:
        for raw in sends:
            await ws.send_str(raw)
        while not done(got):
            msg = await ws.receive(timeout=10)
            if msg.type != aiohttp.WSMsgType.TEXT:
                return got, ws.close_code, msg.extra or ""
            got.append(json.loads(msg.data))
        await ws.close()
        return got, ws.close_code, ""


def acked(n: int) -> Callable[[list[dict]], bool]:
    return lambda got: sum(m["type"] == "ack" for m in got) >= n


def test_the_proxy_relays_a_teaching_servers_acks_and_says_why_it_closes(served, monkeypatch):
    study, server = served
    session = TeachingSession(actions_per_s=5.0)
    session.info = {"weight_name": "Weight", "weight_sentence": "w: fusion=human_only (thesis eq. 4.2)"}
    teacher = TeachingServer(session, port=0, token="worker-secret-token")
    teacher.start()
    real = study.teaching_endpoint
    # the worker's run is the TeachingServer above; the fake train.py only holds the teaching step
    monkeypatch.setattr(
        study,
        "teaching_endpoint",
        lambda code: (teacher.port, teacher.token) if real(code) is not None else None,
    )
    code = join(server)
    url = f"ws://127.0.0.1:{server.port}/p/{code}/teach/ws?tab=t1"
    origin = f"http://127.0.0.1:{server.port}"
    got, close, why = asyncio.run(_teach(url, origin, []))
    assert close == OVER and "not started" in why  # before the teaching step
    try:
        to_teaching(server, code)
        wait_for(lambda: api(server, "GET", f"/p/{code}/api/state")[1]["teaching"]["ready"])
        presses = [json.dumps({"type": "feedback", "value": v, "id": i}) for i, v in enumerate((1, -1, 1))]
        got, _, _ = asyncio.run(_teach(url, origin, presses, acked(3)))
        acks = [m for m in got if m["type"] == "ack"]
        assert [m["id"] for m in acks] == [0, 1, 2] and acks[-1]["given"] == 3
        assert got[0]["type"] == "config" and session.taken == 3
        assert "weight_sentence" not in got[0] and "fusion" not in json.dumps(got)  # blind to the condition
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:  # a page of another origin
            asyncio.run(_teach(url, "http://evil.example", [json.dumps({"type": "finish"})]))
        assert refused.value.status == 403 and session.ending is None
    finally:
        teacher.stop()
    assert session.taken == 3
    got, close, why = asyncio.run(_teach(url, origin, []))
    assert close == WAIT and why  # the run's server has gone: the page is told, and tries again
    request(server, "POST", f"/admin/api/participants/{code}/stop", headers=bearer(study))
    got, close, why = asyncio.run(_teach(url, origin, []))
    assert close == WAIT and "paused" in why
    assert server.errors == 0


def test_a_run_ending_reaches_the_page_then_the_study_goes_on(served, monkeypatch):
    study, server = served
    session = TeachingSession(actions_per_s=5.0)
    teacher = TeachingServer(session, port=0, token="worker-secret-token")
    teacher.start()
    real = study.teaching_endpoint
    monkeypatch.setattr(
        study, "teaching_endpoint", lambda code: (teacher.port, teacher.token) if real(code) else None
    )
    code = join(server)
    to_teaching(server, code)
    wait_for(lambda: api(server, "GET", f"/p/{code}/api/state")[1]["teaching"]["ready"])
    url = f"ws://127.0.0.1:{server.port}/p/{code}/teach/ws"
    origin = f"http://127.0.0.1:{server.port}"

    async def page_sees_the_end() -> tuple[list[dict], int | None]:
        got: list[dict] = []
        async with aiohttp.ClientSession() as client, client.ws_connect(url, origin=origin) as ws:
            await ws.send_str(json.dumps({"type": "feedback", "value": 1, "id": 7}))
            while not any(m["type"] == "ack" for m in got):
                got.append(json.loads((await ws.receive(timeout=10)).data))
            await asyncio.get_running_loop().run_in_executor(
                None, teacher.stop, lambda: session.summary("finished_by_you")
            )
            async for msg in ws:
                got.append(json.loads(msg.data))
            return got, ws.close_code

    got, close = asyncio.run(page_sees_the_end())
    assert got[-1]["type"] == "end" and got[-1]["given"] == 1 and close == WAIT
    (study.directory / "participants" / code / "finish").touch()
    wait_for(lambda: api(server, "GET", f"/p/{code}/api/state")[1]["step"] == "questionnaire")
    got, close, why = asyncio.run(_teach(url, origin, []))
    assert close == OVER and "ended" in why
    assert server.errors == 0


def test_a_page_that_never_reads_holds_up_no_one(served, monkeypatch):
    """Participant A's page stops reading while A's run sends it large frames: A's presses still reach A's
    run, and B's presses are acknowledged promptly through the same study server."""
    study, server = served
    sessions = {name: TeachingSession(actions_per_s=5.0) for name in "AB"}
    teachers = {
        name: TeachingServer(s, port=0, token=f"token-{name}-0123456789") for name, s in sessions.items()
    }
    for teacher in teachers.values():
        teacher.start()
    codes = {join(server): "A", join(server): "B"}
    real = study.teaching_endpoint
    endpoints = {code: (teachers[n].port, teachers[n].token) for code, n in codes.items()}
    monkeypatch.setattr(study, "teaching_endpoint", lambda code: endpoints[code] if real(code) else None)
    for code in codes:
        to_teaching(server, code)
    wait_for(lambda: all(real(code) is not None for code in codes))
    a, b = list(codes)
    origin = f"http://127.0.0.1:{server.port}"
    stop = threading.Event()

    def flood() -> None:  # A's run shows 50 KB frames, as fast as its server sends them
        blob = "x" * 50_000
        while not stop.is_set():
            sessions["A"].publish({"type": "status", "text": blob})
            time.sleep(0.005)

    async def scenario() -> list[float]:
        async with aiohttp.ClientSession() as client:
            stalled = await client.ws_connect(f"ws://127.0.0.1:{server.port}/p/{a}/teach/ws", origin=origin)
            await asyncio.sleep(
                4.0
            )  # A's page reads nothing: the study's buffer to it fills (~270 KB measured)
            for i in range(5):
                await stalled.send_str(json.dumps({"type": "feedback", "value": 1, "id": i}))
            waits = []
            async with client.ws_connect(f"ws://127.0.0.1:{server.port}/p/{b}/teach/ws", origin=origin) as ws:
                for i in range(10):
                    sent = time.monotonic()
                    await ws.send_str(json.dumps({"type": "feedback", "value": -1, "id": i}))
                    while True:
                        m = json.loads((await ws.receive(timeout=10)).data)
                        if m["type"] in ("ack", "error") and m.get("id") == i:
                            waits.append(time.monotonic() - sent)
                            break
                    await asyncio.sleep(0.1)
            await stalled.close()
            return waits

    flooding = threading.Thread(target=flood, daemon=True)
    flooding.start()
    try:
        waits = asyncio.run(scenario())
        wait_for(lambda: sessions["A"].taken == 5, timeout=5)
    finally:
        stop.set()
        flooding.join()
        for teacher in teachers.values():
            teacher.stop()
    assert sessions["B"].taken == 10 and max(waits) < 1.0, waits
    assert server.errors == 0


def test_a_runs_nan_reaches_the_researcher_as_null_in_strict_json(served):
    """A run's metrics may hold NaN, which a browser's JSON parser refuses: the table gets null instead."""
    study, server = served
    code = join(server)
    run = study.directory / "participants" / code / "run"
    run.mkdir(parents=True, exist_ok=True)
    (run / "metrics.jsonl").write_text('{"iteration": 1, "loss": NaN, "lines": 2.0}\n')

    def strict(name: str) -> None:
        raise ValueError(f"{name} is not JSON")

    status, _, body = request(server, "GET", "/admin/api/participants", headers=bearer(study))
    rows = json.loads(body, parse_constant=strict)
    assert status == 200 and rows[0]["progress"] == {"iteration": 1, "loss": None, "lines": 2.0}


def test_a_taken_port_is_one_error_and_leaves_nothing_open(served, caplog):
    """A second study server on the first one's port raises OSError naming the address, and closes the web
    client it opened for its relays (before: 'Unclosed client session' logged seconds later)."""
    study, first = served
    second = StudyServer(study, port=first.port)
    with pytest.raises(OSError, match=f"cannot serve .* on 127.0.0.1:{first.port}"):
        second.start()
    assert second._client is None or second._client.closed
    gc.collect()
    assert "Unclosed client session" not in caplog.text
