"""10,000 hostile and valid messages through the real server (a real socket): no unhandled exception, no
dropped connection, every message answered, and every acknowledged press in the feedback log after stop."""

from __future__ import annotations

import asyncio
import json
import logging
import random
import threading

import aiohttp

from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.interactive.live import LiveTeaching
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.trainers.queue_trainer import QueueTrainer

TEACHER_MESSAGES = 9_000
WATCHER_MESSAGES = 1_000


def _valid(rng: random.Random) -> tuple[str, float | None]:
    """A message the server takes (unless rate-limited), and its press value (None: not a press)."""
    kind = rng.randrange(5)
    if kind < 2:
        value = rng.choice([1, -1, 1.0, -1.0])
        return json.dumps({"type": "feedback", "value": value}), float(value)
    if kind == 2:
        return json.dumps({"type": "speed", "actions_per_s": rng.choice([0.5, 3, 7.25, 20])}), None
    if kind == 3:
        return json.dumps({"paused": rng.random() < 0.5, "type": "pause"}), None
    return json.dumps({"type": "presence", "here": True}), None


def _invalid(rng: random.Random) -> str | bytes:
    """A message the server must refuse: wrong types, unbounded numbers, bad JSON, binary..."""
    values = [
        "9" * rng.randint(7, 2000),
        "1e400",
        "-1e999",
        "NaN",
        "Infinity",
        '"1"',
        "true",
        "null",
        "[]",
        "{}",
    ]
    values += ["0", "2", "-2", "1.0000001", '{"a": 1}', "[1]", "21", "0.49", "1" + "0" * 30]
    fields = ["type", "value", "actions_per_s", "paused", "here", "extra", ""]
    kinds = [  # with "value": 1, only "feedback" would make a valid message
        '"speed"',
        '"pause"',
        '"presence"',
        '"shout"',
        "[]",
        "{}",
        "1",
        "null",
        '"FEEDBACK"',
    ]
    pick = rng.randrange(10)
    if pick == 0:
        return bytes(rng.randrange(256) for _ in range(rng.randint(0, 40)))  # a binary frame
    if pick == 1:
        return "".join(rng.choice('[{]}",:9e.-\\ ntrufalse') for _ in range(rng.randint(0, 60)))
    if pick == 2:
        return "[" * rng.randint(5, 500) + "]" * rng.randint(0, 500)
    if pick == 3:
        return json.dumps(
            {"type": "feedback", "value": 1, "pad": "x" * rng.randint(1100, 30000)}
        )  # too large
    if pick == 4:
        return f'{{"type": {rng.choice(kinds)}, "value": 1}}'
    body = {rng.choice(fields): None for _ in range(rng.randint(0, 3))}
    text = "{" + ", ".join(f'"{k}": {rng.choice(values)}' for k in body) + "}"
    if pick == 5:
        return text
    key = {"feedback": "value", "speed": "actions_per_s", "pause": "paused", "presence": "here"}
    kind = rng.choice(list(key))
    valid_there = {"speed": {"2", "1.0000001"}, "pause": {"true"}, "presence": {"true"}, "feedback": set()}
    wrong = [v for v in values if v not in valid_there[kind]]
    return f'{{"type": "{kind}", "{key[kind]}": {rng.choice(wrong)}}}'


async def _send_and_read(ws, messages: list[str | bytes]) -> list[dict]:
    """Send every message while reading the replies (ack or error), until one reply per message."""
    replies: list[dict] = []

    async def read() -> None:
        while len(replies) < len(messages):
            msg = await ws.receive(timeout=30)
            assert msg.type == aiohttp.WSMsgType.TEXT, f"connection dropped: {msg}"
            m = json.loads(msg.data)
            if m["type"] in ("ack", "error"):
                replies.append(m)

    reader = asyncio.ensure_future(read())
    for raw in messages:
        await (ws.send_bytes(raw) if isinstance(raw, bytes) else ws.send_str(raw))
    await reader
    return replies


def test_ten_thousand_messages_no_exception_no_acknowledged_press_lost(tmp_path, caplog):
    rng = random.Random(2020)
    plan: list[tuple[str | bytes, float | None, bool]] = []  # message, press value, valid
    for _ in range(TEACHER_MESSAGES):
        if rng.random() < 0.4:
            raw, press = _valid(rng)
            plan.append((raw, press, True))
        else:
            plan.append((_invalid(rng), None, False))
    watcher = [_valid(rng)[0] for _ in range(WATCHER_MESSAGES)]

    ticks = iter(range(10**9))
    session = TeachingSession()
    log = FeedbackLog(tmp_path / "feedback.jsonl", "fuzz", fsync=False)
    server = TeachingServer(
        session,
        port=0,
        max_messages_per_s=400,
        clock=lambda: next(ticks) * 0.002,  # 0.8 tokens a message
    )
    server.start()
    teaching = LiveTeaching(server, session, QueueTrainer(session.queue, log=log))
    stop_frames = threading.Event()

    def loop_side() -> None:  # the training loop: frames for the pages, and it drains the queue now and then
        i = 0
        while not stop_frames.wait(0.005):
            i += 1
            session.publish({"type": "status", "text": f"step {i}"})
            if i % 20 == 0:
                log.extend(session.queue.drain())

    frames = threading.Thread(target=loop_side)
    frames.start()
    origin = f"http://127.0.0.1:{server.port}"

    async def run() -> tuple[list[dict], list[dict]]:
        async with aiohttp.ClientSession() as client:
            teacher = await client.ws_connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin)
            watch = await client.ws_connect(f"ws://127.0.0.1:{server.port}/ws", origin=origin)
            got = await asyncio.gather(
                _send_and_read(teacher, [m for m, _, _ in plan]), _send_and_read(watch, watcher)
            )
            await teacher.close()
            await watch.close()
            return got[0], got[1]

    with caplog.at_level(logging.WARNING):
        replies, watched = asyncio.run(run())
        stop_frames.set()
        frames.join()
        teaching.stop()
    log.close()

    assert len(replies) == TEACHER_MESSAGES and len(watched) == WATCHER_MESSAGES
    acked = [press for (_, press, _), r in zip(plan, replies, strict=True) if r["type"] == "ack" and press]
    for (raw, _, valid), r in zip(plan, replies, strict=True):
        assert valid or r["type"] == "error", raw
        assert r["type"] == "ack" or (len(r["message"]) < 300 and "\n" not in r["message"])
    assert all(r["type"] == "error" and "only watches" in r["message"] for r in watched)
    assert server.errors == 0
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert [e.value for e in events] == acked  # every acknowledged press, in order, once
    assert 1000 < len(acked) < sum(1 for _, press, _ in plan if press)  # some rate-limited, most taken
