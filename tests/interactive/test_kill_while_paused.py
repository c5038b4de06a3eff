"""kill -9 of train.py while the person has paused the agent: every press acknowledged before the kill is in
the feedback log exactly once after the run is started again (resume=), although the loop drained none of
them and the run had not finished its first chunk."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import threading
from collections import deque
from pathlib import Path

import aiohttp

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.feedback.log import load_feedback_log

ROOT = Path(__file__).resolve().parents[2]


def _url(proc: subprocess.Popen, said: deque[str]) -> str:
    assert proc.stderr is not None
    for line in proc.stderr:
        said.append(line)
        if "Teach the agent in your browser:" in line:
            threading.Thread(target=said.extend, args=(proc.stderr,), daemon=True).start()
            return line.split("browser:", 1)[1].strip()
    raise AssertionError("train.py did not print the page's URL:\n" + "".join(said))


async def _pause_and_press(url: str, presses: int) -> list[dict]:
    """Connect as the teacher, let the game show, pause, then press below the rate limit; the acks."""
    origin = url.split("/?")[0].rstrip("/")
    acks: list[dict] = []
    async with aiohttp.ClientSession() as client, client.ws_connect(f"{origin}/ws", origin=origin) as ws:

        async def reply(kind: str) -> dict:
            while True:
                m = json.loads((await ws.receive(timeout=30)).data)
                if m["type"] in ("ack", "error") and (m["type"] == "error" or m["message"] == kind):
                    return m

        while json.loads((await ws.receive(timeout=60)).data).get("type") != "keepaway":
            pass  # the first frame of the game is on screen
        await asyncio.sleep(1.0)
        await ws.send_str(json.dumps({"type": "pause", "paused": True}))
        assert (await reply("pause"))["type"] == "ack"
        for i in range(presses):
            await asyncio.sleep(0.06)  # under the 20 messages a second the page may send
            await ws.send_str(json.dumps({"type": "feedback", "value": -1 if i % 3 else 1, "id": i}))
            m = await reply("feedback")
            assert m["type"] == "ack", m
            acks.append(m)
    return acks


def test_presses_acknowledged_while_paused_survive_kill_9_exactly_once(tmp_path):
    run_dir = tmp_path / "run"
    args = [sys.executable, str(ROOT / "train.py"), "domain=keepaway", "trainer=interactive"]
    args += ["trainer.port=0", "trainer.wait_for_page_s=60", "agent.hours=0.05", "agent.table_bits=12"]
    args += ["logger.backend=none", f"hydra.run.dir={run_dir}"]
    said: deque[str] = deque(maxlen=60)
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        acks = asyncio.run(_pause_and_press(_url(proc, said), 30))
        proc.kill()
        proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert len(acks) == 30 and all(a["paused"] for a in acks)
    assert load_checkpoint(run_dir)["history"] == []  # killed within its first chunk
    # started again: the journal's presses go into the log before the resumed learner reads it
    again = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), f"resume={run_dir}"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        _url(again, said)
        again.kill()
        again.wait(timeout=30)
    finally:
        if again.poll() is None:
            again.kill()
    events = load_feedback_log(run_dir / "feedback.jsonl")
    assert [e.value for e in events] == [a["value"] for a in acks]
    assert len({e.id for e in events}) == 30
    assert all(e.source == "human:browser:paused" for e in events)
    assert [(e.episode, e.step) for e in events] == [(a["episode"], a["step"]) for a in acks]
