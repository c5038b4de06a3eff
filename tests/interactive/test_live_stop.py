"""A press acknowledged just before SIGTERM is in the feedback log: the run stops as train.py stops it
(SIGTERM raises KeyboardInterrupt, the loop's ``finally`` stops the teaching, then closes the log)."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import aiohttp

from hfrl_torch.feedback.log import load_feedback_log

REPO = Path(__file__).resolve().parents[2]

_RUN = textwrap.dedent(
    """
    import signal, sys, time
    from hfrl_torch.feedback.log import FeedbackLog
    from hfrl_torch.interactive.live import LiveTeaching
    from hfrl_torch.interactive.server import TeachingServer
    from hfrl_torch.interactive.session import TeachingSession
    from hfrl_torch.trainers.queue_trainer import QueueTrainer

    def interrupt(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, interrupt)
    log = FeedbackLog(sys.argv[1], "sigterm")
    session = TeachingSession()
    server = TeachingServer(session, port=0)
    server.start()
    teaching = LiveTeaching(server, session, QueueTrainer(session.queue, log=log))
    print(server.port, flush=True)
    try:
        while True:  # between watched games: the loop does not drain the queue
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        teaching.stop()
        log.close()
    """
)


async def _press(port: int, n: int) -> list[str]:
    origin = f"http://127.0.0.1:{port}"
    async with aiohttp.ClientSession() as client, client.ws_connect(f"{origin}/ws", origin=origin) as ws:
        replies = []
        for i in range(n):
            await ws.send_str(json.dumps({"type": "feedback", "value": 1 if i % 2 else -1}))
            while True:
                m = json.loads((await ws.receive(timeout=10)).data)
                if m["type"] in ("ack", "error"):
                    replies.append(m["type"])
                    break
        return replies


def test_presses_acknowledged_just_before_sigterm_are_logged(tmp_path):
    path = tmp_path / "feedback.jsonl"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(
        [sys.executable, "-c", _RUN, str(path)], stdout=subprocess.PIPE, text=True, env=env, cwd=REPO
    )
    try:
        assert proc.stdout is not None
        port = int(proc.stdout.readline())
        assert asyncio.run(_press(port, 10)) == ["ack"] * 10
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    events = load_feedback_log(path)
    assert [e.value for e in events] == [-1.0, 1.0] * 5 and {e.source for e in events} == {"human:browser"}
