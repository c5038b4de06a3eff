"""What a real ``study.py`` withstands with two participants teaching: pages that never read (another
participant's, and a second tab of the teacher's own) do not delay the teacher's acknowledgements, and
2,000 idle connections under a 1,024 file-handle limit leave the study, its runs and the teacher's page
working."""

from __future__ import annotations

import asyncio
import json
import random
import resource
import socket
import subprocess
from collections.abc import Iterator
from pathlib import Path

import aiohttp
import pytest
from study_proc import StudyProc, study_args

from hfrl_torch.study import layout
from hfrl_torch.study.client import Participant, Teacher, percentile

pytestmark = pytest.mark.serial  # asserts on acknowledgement latency
# 10x20 boards at 10 placements a second: frames of about 2 kB, 20+ kB a second that a stalled page's
# buffers fill with (the kernel's and the proxy's) within seconds
FAST_TETRIS = ["domain=tetris", "agent=cem", "agent.iterations=50", "agent.population=8"]
FAST_TETRIS += ["agent.games_per_candidate=1", "agent.eval_games=1", "agent.watch_pieces=400"]
FAST_TETRIS += ["domain.height=20", "trainer.actions_per_s=10"]
ACK_P99_MS = 100.0


class Served:
    """The study and its two participants' codes, both in the teaching step with their runs ready."""

    def __init__(self, study: StudyProc, directory: Path, codes: list[str]) -> None:
        self.study = study
        self.directory = directory
        self.codes = codes

    def ws(self, code: str) -> str:
        """The teaching WebSocket of ``code`` through the study's proxy."""
        return self.study.base.replace("http", "ws", 1) + f"/p/{code}/teach/ws"


async def _to_teaching(base: str, n: int) -> list[str]:
    """``n`` scripted participants walked to the teaching step, once their runs accept pages."""
    async with aiohttp.ClientSession() as client:
        people = [Participant(base, seed) for seed in range(n)]
        for p in people:
            p.record.code = await p._join(client)
            state = await p._before_teaching(client, await p._state(client))
            assert state["step"] == "teaching", state
        for p in people:
            state = await p._until(client, lambda s: s["teaching"]["ready"], "the run was not ready")
        return [p.record.code for p in people]


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    """study.py under a 1,024 file-handle limit (its workers inherit it), two participants teaching."""
    tmp = tmp_path_factory.mktemp("limits")
    directory = tmp / "study"
    study = StudyProc(study_args(directory, 2, {"tetris": FAST_TETRIS}), tmp / "study.log", nofile=1024)
    try:
        codes = asyncio.run(_to_teaching(study.base, 2))
        yield Served(study, directory, codes)
    finally:
        study.stop()


def _stalled_page(port: int, code: str) -> socket.socket:
    """A teaching page of ``code`` that opens its WebSocket through the proxy and never reads a byte."""
    s = socket.socket()
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    s.connect(("127.0.0.1", port))
    handshake = [
        f"GET /p/{code}/teach/ws HTTP/1.1",
        f"Host: 127.0.0.1:{port}",
        f"Origin: http://127.0.0.1:{port}",
        "Upgrade: websocket",
        "Connection: Upgrade",
        "Sec-WebSocket-Version: 13",
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==",
    ]
    s.sendall(("\r\n".join(handshake) + "\r\n\r\n").encode())
    return s


def _unsent_bytes(port: int, peers: list[socket.socket]) -> int:
    """Bytes the study server's side still holds for ``peers`` in the kernel (``ss``'s Send-Q)."""
    ports = {p.getsockname()[1] for p in peers}
    out = subprocess.run(["ss", "-tnH", "state", "established"], capture_output=True, text=True).stdout
    held = 0
    for line in out.splitlines():
        fields = line.split()
        if len(fields) >= 4 and fields[2].endswith(f":{port}") and int(fields[3].rsplit(":", 1)[1]) in ports:
            held += int(fields[1])
    return held


def test_pages_that_never_read_do_not_delay_another_participants_acknowledgements(served):
    """The teacher's acknowledgements with three stalled pages open (two of the other participant's, one
    of their own) against the same teacher's just before without them. A page that blocked the relay would
    hold every acknowledgement after it, for seconds. Over 40 presses a p99 is the slowest one alone, and
    about one run in four has a single acknowledgement of 150-200 ms with or without stalled pages (a pause
    of the run itself, source not found); so the limit is on the p95 (100 ms, or twice the p95 without
    stalled pages where that is already over 50 ms) and on the slowest (1 s)."""
    port = int(served.study.base.rsplit(":", 1)[1])
    teacher_code, other = served.codes

    async def measured(stall: bool) -> tuple[Teacher, int]:
        base = served.study.base
        teacher = Teacher(
            served.ws(teacher_code), base, random.Random(7), presses=40, gap_s=(0.14, 0.25), finish=False
        )
        async with aiohttp.ClientSession() as client:
            task = asyncio.ensure_future(teacher.run(client))
            while teacher.role != "teach":  # the teacher's page teaches; the stalled ones come after it
                await asyncio.sleep(0.05)
            stalled = []
            if stall:
                stalled = [_stalled_page(port, other), _stalled_page(port, other)]
                stalled.append(_stalled_page(port, teacher_code))
                await asyncio.sleep(8.0)  # the frames fill the stalled pages' buffers
            held = _unsent_bytes(port, stalled) if stall else 0
            await asyncio.wait_for(task, 120)
            for s in stalled:
                s.close()
        return teacher, held

    p95, slowest = {}, {}
    for stall in (False, True):
        teacher, held = asyncio.run(measured(stall))
        ms = [m for m in (p.ack_ms for p in teacher.record.acked) if m is not None]
        assert len(ms) >= 35, [p.error for p in teacher.record.presses]
        p95[stall], slowest[stall] = percentile(ms, 95), max(ms)
    print(
        f"ack p95 without stalled pages {p95[False]:.1f} ms, with {p95[True]:.1f} ms (slowest "
        f"{slowest[False]:.1f} and {slowest[True]:.1f} ms; {held} bytes held)"
    )
    assert held > 50_000, f"the stalled pages hold only {held} bytes in the kernel: they are not stalled"
    limit = ACK_P99_MS if p95[False] < ACK_P99_MS / 2 else 2 * p95[False]
    assert p95[True] < limit, f"ack p95 {p95[True]:.1f} ms with stalled pages, {p95[False]:.1f} ms without"
    assert slowest[True] < 1000.0, f"an acknowledgement took {slowest[True]:.0f} ms with stalled pages"


def test_two_thousand_idle_connections_under_a_1024_handle_limit_leave_the_study_working(served):
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard != resource.RLIM_INFINITY and hard < 2200:
        pytest.skip(f"this test opens 2,000 sockets; the hard file-handle limit here is {hard}")
    resource.setrlimit(
        resource.RLIMIT_NOFILE, (4096 if hard == resource.RLIM_INFINITY else min(hard, 4096), hard)
    )
    port = int(served.study.base.rsplit(":", 1)[1])
    code = served.codes[0]
    sockets: list[socket.socket] = []

    async def flood_while_teaching() -> tuple[Teacher, dict]:
        base = served.study.base
        teacher = Teacher(served.ws(code), base, random.Random(8), presses=10, gap_s=(0.3, 0.5), finish=False)
        async with aiohttp.ClientSession() as client:
            task = asyncio.ensure_future(teacher.run(client))
            while teacher.role != "teach":
                await asyncio.sleep(0.05)
            for _ in range(2000):  # a loaded machine's accept backlog may make a connect wait
                try:
                    sockets.append(socket.create_connection(("127.0.0.1", port), timeout=30))
                except OSError:
                    break
                if len(sockets) % 200 == 0:
                    await asyncio.sleep(0)  # the teacher's page goes on meanwhile
            await asyncio.wait_for(task, 120)
            for s in sockets:
                s.close()
            async with client.get(f"{base}/p/{code}/api/state") as r:  # the page's own requests work again
                assert r.status == 200
                state = await r.json()
        return teacher, state

    try:
        teacher, state = asyncio.run(flood_while_teaching())
    finally:
        for s in sockets:
            s.close()
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))
    assert len(sockets) == 2000
    # every press is answered; a press the run refuses for a reason a person would be told (the agent
    # practising between games when a loaded machine delivered the frame late) is not a failure of the study
    errors = [p.error for p in teacher.record.presses if p.error is not None]
    assert all(p.answered is not None for p in teacher.record.presses)
    assert all(e.startswith("not taken: ") for e in errors), errors
    assert len(teacher.record.acked) >= 8, errors
    assert state["step"] == "teaching" and state["teaching"]["ready"]
    assert served.study.proc.poll() is None
    log = (served.directory / layout.PARTICIPANTS / code / layout.WORKER_LOG).read_text()
    assert "Too many open files" not in served.study.log.read_text() + log
    assert json.loads(layout.participant_json(served.directory, code).read_text())["step"] == "teaching"
