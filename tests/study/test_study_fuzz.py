"""Seeded fuzz of the study server: random JSON bodies for joining and for every step (valid step names with
wrong actions and data, and garbage), random paths and methods, and random frames through the teaching proxy.
Every answer is below 500, nothing raises out of a handler and nothing is logged as an ERROR."""

from __future__ import annotations

import asyncio
import http.client
import json
import logging
import random
from pathlib import Path
from urllib.parse import quote

import aiohttp
from study_web import FAKE_TRAIN, study_config, wait_for

from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.study.manager import Study
from hfrl_torch.study.server import StudyServer

STEPS = [
    "consent",
    "instructions",
    "practice",
    "calibration",
    "teaching",
    "questionnaire",
    "done",
    "declined",
]
ACTIONS = ["agree", "decline", "next", "skip", "finish", ""]
SEED = 44


def value(rng: random.Random, depth: int = 0) -> object:
    """A random JSON value: the odd types and bounds a parser meets."""
    kinds = ["int", "float", "str", "bool", "null", "big", "neg"] + (["list", "dict"] if depth < 4 else [])
    kind = rng.choice(kinds)
    if kind == "int":
        return rng.randint(-10, 10)
    if kind == "float":
        return rng.choice([0.0, 0.04, 0.3, 2.9, 3.1, -1.0, 1e300, 1e-300])
    if kind == "str":
        return rng.choice(
            ["", "x" * rng.randint(1, 3000), "é☃\u0000", "<script>", "../../etc/passwd", "effort"]
        )
    if kind == "bool":
        return rng.random() < 0.5
    if kind == "null":
        return None
    if kind == "big":
        return 10 ** rng.randint(5, 40)
    if kind == "neg":
        return -(10 ** rng.randint(1, 12))
    if kind == "list":
        return [value(rng, depth + 1) for _ in range(rng.randint(0, 60))]
    return {
        rng.choice(["effort", "comments", "delays_s", "answers", "x", ""]): value(rng, depth + 1)
        for _ in range(3)
    }


def step_body(rng: random.Random) -> object:
    data_kinds = [
        lambda: {
            "delays_s": [rng.choice([0.01, 0.3, 0.7, 3.5, -1, "a", None]) for _ in range(rng.randint(0, 70))]
        },
        lambda: {"answers": {k: value(rng, 2) for k in rng.sample(["effort", "comments", "nope"], 2)}},
        lambda: {"answers": {"effort": rng.randint(-3, 9), "comments": "y" * rng.randint(0, 80)}},
        lambda: value(rng, 1),
    ]
    body = {"step": rng.choice([*STEPS, value(rng, 3)]), "action": rng.choice([*ACTIONS, value(rng, 3)])}
    if rng.random() < 0.8:
        body["data"] = rng.choice(data_kinds)()
    if rng.random() < 0.1:
        return value(rng)
    return body


def raw_body(rng: random.Random, body: object) -> bytes:
    text = json.dumps(body).encode()
    cut = rng.random()
    if cut < 0.05:
        return text[: rng.randint(0, len(text))]
    if cut < 0.08:
        return b"[" * rng.randint(10, 5000)
    if cut < 0.1:
        return bytes(rng.randrange(256) for _ in range(rng.randint(1, 200)))
    return text


def path(rng: random.Random, codes: list[str]) -> str:
    segments = [
        "p",
        rng.choice(codes),
        "api",
        "state",
        "step",
        "teach",
        "static",
        "admin",
        "ws",
        "..",
        "%2e%2e",
    ]
    segments += ["x" * rng.randint(200, 5000), quote("é☃"), "study.js", "app.js", "data.zip", "participants"]
    return "/" + "/".join(rng.choice(segments) for _ in range(rng.randint(0, 6)))


def test_fuzzed_requests_get_answers_not_exceptions(tmp_path: Path, caplog):
    caplog.set_level(logging.WARNING)
    rng = random.Random(SEED)
    study = Study.open(study_config(tmp_path), tmp_path / "study", train_script=FAKE_TRAIN)
    server = StudyServer(study, port=0, max_requests_per_s=1000, max_joins_per_s=1000, max_misses_per_s=1000)
    server.start()
    statuses: dict[int, int] = {}
    try:
        conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)

        def send(method: str, where: str, body: bytes | None) -> int:
            nonlocal conn
            try:
                conn.request(method, where, body=body, headers={"Content-Type": "application/json"})
                r = conn.getresponse()
                r.read()
            except (http.client.HTTPException, ConnectionError):
                conn.close()  # the server closed a connection it would not serve (e.g. a malformed request)
                conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
                return 0
            statuses[r.status] = statuses.get(r.status, 0) + 1
            if r.will_close:
                conn.close()
                conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
            return r.status

        codes = [study.join(simulated=True).code for _ in range(4)]
        for code, stop_at in zip(codes, (1, 3, 4, 4), strict=True):  # participants at various steps
            for at, action, data in (
                ("consent", "agree", {}),
                ("instructions", "next", {}),
                ("practice", "next", {}),
                ("calibration", "skip", {}),
            )[:stop_at]:
                study.advance(code, at, action, data)
        (study.directory / "participants" / codes[3] / "finish").touch()
        wait_for(lambda: study.get(codes[3]).step == "questionnaire")
        for i in range(1500):
            kind = rng.random()
            if kind < 0.55:
                code = rng.choice([*codes, "NOPE", codes[0].lower()])
                status = send("POST", f"/p/{code}/api/step", raw_body(rng, step_body(rng)))
            elif kind < 0.7:
                status = send(
                    "POST",
                    "/api/join",
                    raw_body(
                        rng, value(rng) if rng.random() < 0.7 else {"simulated": False, "condition": "x"}
                    ),
                )
            else:
                method = rng.choice(["GET", "GET", "POST", "PUT", "DELETE", "HEAD", "OPTIONS"])
                status = send(
                    method, path(rng, codes), raw_body(rng, value(rng)) if method == "POST" else None
                )
            assert status < 500, (i, status)
    finally:
        conn.close()
        server.stop()
        study.close(timeout=5)
    assert server.errors == 0
    assert sum(statuses.values()) > 1400 and statuses.get(200, 0) > 0 and statuses.get(400, 0) > 100
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


def test_fuzzed_frames_through_the_teaching_proxy(tmp_path: Path, caplog):
    """Random frames relayed to a real TeachingServer: each is answered by the run's own checks, and neither
    the proxy nor the run's server raises."""
    caplog.set_level(logging.WARNING)
    rng = random.Random(SEED + 1)
    study = Study.open(study_config(tmp_path), tmp_path / "study", train_script=FAKE_TRAIN)
    session = TeachingSession()
    teacher = TeachingServer(session, port=0, token="worker-token-for-fuzz", max_messages_per_s=1000)
    teacher.start()
    real = study.teaching_endpoint
    study.teaching_endpoint = lambda code: (teacher.port, teacher.token) if real(code) else None
    server = StudyServer(study, port=0)
    server.start()
    code = study.join(simulated=True).code
    for at, action in (
        ("consent", "agree"),
        ("instructions", "next"),
        ("practice", "next"),
        ("calibration", "skip"),
    ):
        study.advance(code, at, action, {})
    wait_for(lambda: real(code) is not None)

    async def flood() -> int:
        answered = 0
        url = f"ws://127.0.0.1:{server.port}/p/{code}/teach/ws"
        async with aiohttp.ClientSession() as client:
            ws = await client.ws_connect(url, origin=f"http://127.0.0.1:{server.port}")
            frames = 300
            for _ in range(frames):
                message = {
                    "type": rng.choice(["feedback", "speed", "pause", "presence", "x"]),
                    "value": value(rng, 3),
                }
                if rng.random() < 0.3:
                    message = value(rng)
                if rng.random() < 0.1:
                    await ws.send_bytes(bytes(rng.randrange(256) for _ in range(rng.randint(1, 64))))
                else:
                    await ws.send_str(json.dumps(message)[:20000])
            while answered < frames:
                msg = await ws.receive(timeout=10)
                assert msg.type == aiohttp.WSMsgType.TEXT, msg
                answered += json.loads(msg.data)["type"] in ("ack", "error")
            await ws.close()
        return answered

    try:
        assert asyncio.run(flood()) == 300
    finally:
        server.stop()
        teacher.stop()
        study.close(timeout=5)
    assert server.errors == 0 and teacher.errors == 0
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
