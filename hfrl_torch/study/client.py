"""A scripted participant (asyncio + aiohttp), for the study's load benchmark and tests.

:class:`Participant` joins a study (``simulated: true``) or takes a given code, walks consent,
instructions, practice, calibration (delays drawn from gamma(2, 0.28) with its own seed) and, after
teaching, the questionnaire through the study's HTTP API. :class:`Teacher` teaches one run through its
WebSocket, through the study's proxy (``/p/<code>/teach/ws``) or straight to one ``train.py
trainer=interactive`` run (:func:`run_ws`): it presses Good or Bad at a person's pace while something is
on screen to judge, records each press's send and acknowledgement times (or the reason it was not
taken), and ends with Finish and save after a set number of presses, a set time, or when the run ends.

**Late frames.** A frame is the run's picture of the game (``tetris`` or ``keepaway`` messages). The
*announced period* is what the run's settings say one frame lasts: Tetris shows one placement per
action, ``1 / actions_per_s``; keepaway one simulator cycle, ``KEEPAWAY_CYCLE_S * real_time /
actions_per_s`` (``real_time``: the decisions per second that play at real time, from the frame). A
*steady gap* is the time between the arrival of two consecutive frames of the same game (Tetris) or
episode (keepaway) with nothing else shown between them and the run playing at pace all along: this page
teaching, the run live, not paused, the person here, not ending and the speed unchanged. A steady gap is
*late* when it exceeds ``LATE_FACTOR`` (1.5) times the announced period; ``frame_late_share`` is late
gaps over steady gaps.

:func:`check_presses` compares the acknowledged presses with the run's press journal (``presses.jsonl``)
and feedback log (``feedback.jsonl``): each acknowledged press must be journaled and logged exactly once.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import aiohttp

from hfrl_torch.feedback.log import read_feedback_log
from hfrl_torch.interactive.journal import JOURNAL_NAME, read_journal
from hfrl_torch.interactive.messages import MAX_PRESS_ID
from hfrl_torch.interactive.session import PAUSED_SOURCE

LATE_FACTOR = 1.5
KEEPAWAY_CYCLE_S = 0.1  # one simulator cycle of keepaway at real time
PRESS_GAP_S = (0.7, 1.5)  # a person's pace: one press every 0.7-1.5 s while there is something to judge
GAMMA_SHAPE, GAMMA_SCALE = 2.0, 0.28  # the scripted reaction delays of the calibration
DELAY_BOUNDS_S = (0.05, 3.0)  # what the study accepts for one calibration delay
GAME_FRAMES = ("tetris", "keepaway")
STEADY_KEYS = ("actions_per_s", "paused", "here", "live", "ending")
STEPS_BEFORE_TEACHING = ("consent", "instructions", "practice", "calibration")
WALL_SLACK_S = 0.05  # a journaled press's wall time lies within its send and ack times, give or take this


@dataclass
class PressRecord:
    """One press as the client saw it: its id, value, when it was sent and answered (``time.monotonic``
    and ``time.time``), and the acknowledgement (None: none) or the reason it was not taken."""

    id: int
    value: float
    sent: float
    sent_wall: float
    answered: float | None = None
    answered_wall: float | None = None
    ack: dict[str, Any] | None = None
    error: str | None = None

    @property
    def ack_ms(self) -> float | None:
        """Milliseconds from sending to the acknowledgement (None: not acknowledged)."""
        if self.ack is None or self.answered is None:
            return None
        return 1000.0 * (self.answered - self.sent)


@dataclass
class TeachRecord:
    """What one teaching session gave: the presses, frames counted, steady and late frame gaps (see the
    module), the run's end message (None: none came) and the other errors the run sent."""

    presses: list[PressRecord] = field(default_factory=list)
    frames: int = 0
    steady_gaps: int = 0
    late_gaps: int = 0
    worst_gap_ratio: float = 0.0
    end: dict[str, Any] | None = None
    connections: int = 0
    errors: list[str] = field(default_factory=list)

    @property
    def acked(self) -> list[PressRecord]:
        """The presses the run acknowledged, in order."""
        return [p for p in self.presses if p.ack is not None]


class Teacher:
    """Teaches one run through its WebSocket at a person's pace; :attr:`record` fills in as it goes (it
    stays readable when the task is cancelled, e.g. when a test kills the run under it).

    :param ws_url: the run's WebSocket (``ws://.../ws?token=...`` or the study's ``.../teach/ws``).
    :param origin: the ``Origin`` the page would send (the server that served the page).
    :param rng: the presses' gaps and values are drawn from it.
    :param presses: send Finish and save after this many presses are sent and answered (None: no limit).
    :param seconds: send Finish and save this long after the first frame to judge (None: no limit).
    :param gap_s: each press waits a gap drawn uniformly from this range after the last.
    :param good_share: the share of presses that are Good.
    :param pause_after: pause the run once this many presses are acknowledged, and go on pressing.
    :param finish: send Finish and save at the end (False: just close the page).
    :param connect_s: how long a refused or dropped connection is retried before giving up.
    """

    def __init__(
        self,
        ws_url: str,
        origin: str,
        rng: random.Random,
        presses: int | None = 20,
        seconds: float | None = None,
        gap_s: tuple[float, float] = PRESS_GAP_S,
        good_share: float = 0.7,
        pause_after: int | None = None,
        finish: bool = True,
        connect_s: float = 60.0,
    ) -> None:
        if not 0 < gap_s[0] <= gap_s[1]:
            raise ValueError(f"gap_s={gap_s!r} is invalid: must be (low, high) with 0 < low <= high")
        self.ws_url = ws_url
        self.origin = origin
        self.rng = rng
        self.presses = presses
        self.seconds = seconds
        self.gap_s = gap_s
        self.good_share = good_share
        self.pause_after = pause_after
        self.finish = finish
        self.connect_s = connect_s
        self.record = TeachRecord()
        self.settings: dict[str, Any] = {}
        self.role = ""
        self.paused_ack = asyncio.Event()
        self._pending: deque[PressRecord | str] = deque()  # what each next ack or error answers
        self._last_frame: tuple[float, Any] | None = None  # (arrival, game or episode) of a steady frame
        self._period: float | None = None
        self._judge = asyncio.Event()  # something is on screen to judge
        self._ended = asyncio.Event()
        self._first_judge: float | None = None
        self._showing_since: float | None = None  # arrival of the first game frame since anything else
        self.reaction_s = 0.3
        self._next_id = 0
        self._finish_sent = False

    # --- receiving ---

    def _steady(self) -> bool:
        s = self.settings
        return (
            self.role == "teach"
            and bool(s.get("live"))
            and not s.get("paused")
            and s.get("here", True)
            and s.get("ending") is None
        )

    def _on_settings(self, message: dict[str, Any]) -> None:
        if any(message.get(k) != self.settings.get(k) for k in STEADY_KEYS):
            self._last_frame = None
        if not message.get("live"):
            self._showing_since = None
        self.settings = message
        self._update_judge()

    def _update_judge(self) -> None:
        s = self.settings
        if self.role == "teach" and s.get("live") and s.get("here", True) and s.get("ending") is None:
            self._judge.set()
        else:
            self._judge.clear()

    def _on_frame(self, message: dict[str, Any], now: float) -> None:
        self.record.frames += 1
        speed = float(self.settings.get("actions_per_s") or 0.0)
        if message["type"] == "tetris":
            unit, period = message.get("game"), (1.0 / speed if speed else None)
        else:
            real_time = float(message.get("real_time") or 0.0)
            unit = message.get("episode")
            period = KEEPAWAY_CYCLE_S * real_time / speed if speed and real_time else None
        steady = self._steady() and message.get("phase", "watch") == "watch" and period is not None
        if steady and self._last_frame is not None and self._last_frame[1] == unit:
            assert period is not None
            ratio = (now - self._last_frame[0]) / period
            self.record.steady_gaps += 1
            self.record.late_gaps += ratio > LATE_FACTOR
            self.record.worst_gap_ratio = max(self.record.worst_gap_ratio, ratio)
        self._last_frame = (now, unit) if steady else None
        if self._showing_since is None:
            self._showing_since = now
        if self._first_judge is None and self._judge.is_set():
            self._first_judge = now

    def _on_answer(self, message: dict[str, Any], now: float) -> None:
        if not self._pending:
            self.record.errors.append(f"an answer to nothing sent: {json.dumps(message)[:200]}")
            return
        head = self._pending.popleft()
        if isinstance(head, str):  # a pause or finish
            if message["type"] == "ack" and head == "pause":
                self.paused_ack.set()
            elif message["type"] == "error":
                self.record.errors.append(f"{head}: {message.get('message')}")
            return
        if message.get("id", head.id) != head.id:
            self.record.errors.append(f"press {head.id} answered with id {message.get('id')}")
        head.answered, head.answered_wall = now, time.time()
        if message["type"] == "ack":
            head.ack = message
        else:
            head.error = str(message.get("message"))

    def _on_message(self, message: dict[str, Any], now: float) -> None:
        kind = message.get("type")
        if kind in GAME_FRAMES:
            self._on_frame(message, now)
        elif kind == "status":
            self._last_frame = self._showing_since = None
        elif kind == "config":
            self.reaction_s = float(message.get("reaction_s", self.reaction_s))
        elif kind == "settings":
            self._on_settings(message)
        elif kind == "role":
            self.role = str(message.get("role"))
            self._last_frame = None
            self._update_judge()
        elif kind in ("ack", "error"):
            self._on_answer(message, now)
        elif kind == "end":
            self.record.end = message
            self._ended.set()
            self._judge.set()

    async def _read(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        async for msg in ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                break
            self._on_message(json.loads(msg.data), time.monotonic())

    # --- sending ---

    async def _send(
        self, ws: aiohttp.ClientWebSocketResponse, obj: dict[str, Any], what: PressRecord | str
    ) -> None:
        self._pending.append(what)
        await ws.send_str(json.dumps(obj))

    def _done(self) -> bool:
        if self.presses is not None and len(self.record.presses) >= self.presses:
            return True  # sent, not answered: an answer slower than the gap must not let one more through
        if self.seconds is not None and self._first_judge is not None:
            return time.monotonic() - self._first_judge >= self.seconds
        return False

    async def _press(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        while not self._ended.is_set() and not self._done():
            await self._judge.wait()
            if self._ended.is_set():
                return
            await asyncio.sleep(self.rng.uniform(*self.gap_s))
            if not self._judge.is_set() or self._ended.is_set() or self._done():
                continue
            if self._showing_since is None or time.monotonic() - self._showing_since < self.reaction_s:
                continue  # a person judges what they saw: a game on screen at least their reaction time
            acked = len(self.record.acked)
            if self.pause_after is not None and acked >= self.pause_after and not self.paused_ack.is_set():
                if "pause" not in self._pending:
                    await self._send(ws, {"type": "pause", "paused": True}, "pause")
                continue
            value = 1.0 if self.rng.random() < self.good_share else -1.0
            press = PressRecord(self._next_id, value, time.monotonic(), time.time())
            self._next_id = (self._next_id + 1) % (MAX_PRESS_ID + 1)
            self.record.presses.append(press)
            await self._send(ws, {"type": "feedback", "value": value, "id": press.id}, press)
        if not self.finish and not self._ended.is_set():  # the page closes once its presses are answered
            while any(isinstance(p, PressRecord) for p in self._pending):
                await asyncio.sleep(0.05)
            await ws.close()
            return
        if not self._ended.is_set() and not self._finish_sent:
            while any(isinstance(p, PressRecord) for p in self._pending):  # the last presses' answers
                await asyncio.sleep(0.05)
            self._finish_sent = True
            await self._send(ws, {"type": "finish"}, "finish")

    async def _connect(self, client: aiohttp.ClientSession) -> aiohttp.ClientWebSocketResponse:
        deadline = time.monotonic() + self.connect_s
        while True:
            try:
                return await client.ws_connect(self.ws_url, origin=self.origin, heartbeat=None)
            except (aiohttp.WSServerHandshakeError, aiohttp.ClientConnectionError) as e:
                if time.monotonic() > deadline:
                    raise ConnectionError(f"cannot open {self.ws_url}: {e}") from e
                await asyncio.sleep(0.5)

    def _pressing_ended(self, task: asyncio.Future[None]) -> None:
        if not task.cancelled() and task.exception() is not None:
            error = task.exception()
            self.record.errors.append(f"pressing stopped: {type(error).__name__}: {error}")

    async def run(self, client: aiohttp.ClientSession) -> TeachRecord:
        """Teach until the run ends (its ``end`` message, or Finish and save answered); a connection that
        drops before is opened again (for up to ``connect_s``). Returns :attr:`record`."""
        while not self._ended.is_set():
            ws = await self._connect(client)
            self.record.connections += 1
            self._pending.clear()
            self._last_frame = self._showing_since = None
            self.role, self.settings = "", {}
            self._judge.clear()
            presser = asyncio.ensure_future(self._press(ws))
            presser.add_done_callback(self._pressing_ended)
            try:
                await self._read(ws)
            finally:
                presser.cancel()
                with contextlib.suppress(asyncio.CancelledError, ConnectionError, RuntimeError):
                    await presser
                await ws.close()
            if self._finish_sent or (not self.finish and self._done()):
                break
        for press in self.record.presses:
            if press.answered is None and press.error is None:
                press.error = "no answer: the connection closed"
        return self.record


def ws_of(url: str) -> tuple[str, str]:
    """The WebSocket URL and the page's Origin of a run's printed page URL (``http://host:port/?token=``)."""
    parts = urlsplit(url)
    origin = f"{parts.scheme}://{parts.netloc}"
    scheme = "wss" if parts.scheme == "https" else "ws"
    return f"{scheme}://{parts.netloc}{parts.path.rstrip('/')}/ws" + (
        f"?{parts.query}" if parts.query else ""
    ), origin


async def run_ws(url: str, rng: random.Random, **teacher: Any) -> TeachRecord:
    """Teach one ``train.py trainer=interactive`` run straight through the URL it printed."""
    ws_url, origin = ws_of(url)
    async with aiohttp.ClientSession() as client:
        return await Teacher(ws_url, origin, rng, **teacher).run(client)


@dataclass
class ParticipantRecord:
    """A scripted participant's way through a study: its code, the steps it saw, its teaching session
    and whether it reached ``done``."""

    code: str = ""
    steps: list[str] = field(default_factory=list)
    teaching: TeachRecord | None = None
    delays_s: list[float] = field(default_factory=list)
    answers: dict[str, Any] = field(default_factory=dict)
    done: bool = False
    error: str | None = None


class Participant:
    """One scripted participant of a study served at ``base`` (``http://127.0.0.1:<port>``).

    :param base: the study's address.
    :param seed: seeds the calibration delays, the answers and the presses.
    :param code: a participant code to use (None: join, as a simulated participant).
    :param poll_s: how often the study's state is read while waiting (the run starting, the run ending).
    :param wait_s: how long each such wait may last.
    :param teacher: :class:`Teacher`'s options (``presses``, ``seconds``, ``gap_s``, ...).
    """

    def __init__(
        self,
        base: str,
        seed: int,
        code: str | None = None,
        poll_s: float = 0.5,
        wait_s: float = 300.0,
        **teacher: Any,
    ) -> None:
        self.base = base.rstrip("/")
        self.rng = random.Random(seed)
        self.poll_s = poll_s
        self.wait_s = wait_s
        self.teacher_options = teacher
        self.teacher: Teacher | None = None
        self.record = ParticipantRecord(code=code or "")

    def _url(self, path: str) -> str:
        return f"{self.base}/p/{self.record.code}/{path}"

    async def _join(self, client: aiohttp.ClientSession) -> str:
        """A new code; a busy study (429, 503) is asked again, as a person would press Start again."""
        deadline = time.monotonic() + self.wait_s
        while True:
            async with client.post(f"{self.base}/api/join", json={"simulated": True}) as r:
                if r.status == 200:
                    return str((await r.json())["code"])
                if r.status not in (429, 503) or time.monotonic() > deadline:
                    raise RuntimeError(f"join answered {r.status}: {(await r.text())[:200]}")
            await asyncio.sleep(self.rng.uniform(0.5, 1.5))

    async def _state(self, client: aiohttp.ClientSession) -> dict[str, Any]:
        async with client.get(self._url("api/state")) as r:
            if r.status != 200:
                raise RuntimeError(f"GET state answered {r.status}: {(await r.text())[:200]}")
            return await r.json()

    async def _step(
        self, client: aiohttp.ClientSession, step: str, action: str, data: dict[str, Any] | None = None
    ) -> dict[str, Any]:
        body = {"step": step, "action": action, "data": data or {}}
        async with client.post(self._url("api/step"), json=body) as r:
            if r.status not in (200, 409):
                raise RuntimeError(f"step {step}/{action} answered {r.status}: {(await r.text())[:200]}")
            return await r.json()

    def _delays(self, trials: int) -> list[float]:
        low, high = DELAY_BOUNDS_S
        return [
            round(min(max(self.rng.gammavariate(GAMMA_SHAPE, GAMMA_SCALE), low), high), 3)
            for _ in range(trials)
        ]

    def _answers(self, items: list[dict[str, Any]]) -> dict[str, Any]:
        answers: dict[str, Any] = {}
        for item in items:
            if item.get("kind") == "likert":
                answers[item["id"]] = self.rng.randint(1, int(item.get("points", 7)))
            else:
                answers[item["id"]] = f"scripted participant {self.record.code}"[
                    : int(item.get("max_chars", 200))
                ]
        return answers

    async def _until(self, client: aiohttp.ClientSession, done: Any, what: str) -> dict[str, Any]:
        deadline = time.monotonic() + self.wait_s
        while True:
            state = await self._state(client)
            if done(state):
                return state
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f"participant {self.record.code}: {what} within {self.wait_s:g} s "
                    f"(step {state.get('step')})"
                )
            await asyncio.sleep(self.poll_s)

    async def _before_teaching(self, client: aiohttp.ClientSession, state: dict[str, Any]) -> dict[str, Any]:
        while state["step"] in STEPS_BEFORE_TEACHING:
            step = state["step"]
            self.record.steps.append(step)
            if step == "consent":
                state = await self._step(client, step, "agree")
            elif step == "calibration":
                trials = int(state["study"].get("calibration", {}).get("trials", 0))
                self.record.delays_s = self._delays(trials)
                await asyncio.sleep(min(sum(self.record.delays_s), 5.0))
                state = await self._step(client, step, "next", {"delays_s": self.record.delays_s})
            else:
                await asyncio.sleep(self.rng.uniform(0.2, 0.6))  # reading, or the practice round
                state = await self._step(client, step, "next")
        return state

    async def run(self, client: aiohttp.ClientSession) -> ParticipantRecord:
        """Join (unless a code was given), go through every step to ``done``; :attr:`record` says how far
        it got (``error``: why it stopped)."""
        try:
            if not self.record.code:
                self.record.code = await self._join(client)
            state = await self._before_teaching(client, await self._state(client))
            if state["step"] == "teaching":
                self.record.steps.append("teaching")
                state = await self._until(
                    client,
                    lambda s: s["teaching"]["ready"] or s["step"] != "teaching",
                    "the run was not ready",
                )
                if state["step"] == "teaching":
                    ws_url = self.base.replace("http", "ws", 1) + state["teaching"]["url"].rstrip("/") + "/ws"
                    self.teacher = Teacher(ws_url, self.base, self.rng, **self.teacher_options)
                    self.record.teaching = await self.teacher.run(client)
                    state = await self._until(
                        client, lambda s: s["step"] != "teaching", "the run did not end"
                    )
            if state["step"] == "questionnaire":
                self.record.steps.append("questionnaire")
                self.record.answers = self._answers(state["study"].get("questionnaire", []))
                state = await self._step(client, "questionnaire", "next", {"answers": self.record.answers})
            self.record.steps.append(state["step"])
            self.record.done = state["step"] == "done"
        except Exception as e:  # the record says how far it got and why it stopped
            self.record.error = f"{type(e).__name__}: {e}"
        return self.record


def percentile(values: list[float], q: float) -> float | None:
    """The ``q``-th percentile (0..100) by the nearest-rank rule (None: no values)."""
    if not values:
        return None
    ordered = sorted(values)
    rank = max(1, -(-len(ordered) * q // 100))
    return ordered[int(rank) - 1]


def check_presses(run_dir: Path, presses: list[PressRecord]) -> dict[str, int]:
    """Every acknowledged press of ``presses`` against ``run_dir``'s press journal and feedback log.

    The acknowledged presses, in order, are matched in order to the journal's presses with the same value,
    episode, step and paused flag, journaled between their send and ack times; each match's number ``n``
    must be logged exactly once as event ``n`` of the log's browser session, with the same value and source
    (not the same step: the loop credits a press filed under no frame at the step it drains it at).

    Returns ``acked``, ``journaled``, ``logged`` (browser events in the log), ``lost`` (acknowledged, not
    journaled or not logged), ``duplicated`` (logged events of one number beyond the first, and copies the
    log's reader dropped) and ``unacked_logged`` (logged presses whose acknowledgement never arrived, e.g. a
    kill between the two: not an error)."""
    acked = [p for p in presses if p.ack is not None]
    journal = read_journal(run_dir / JOURNAL_NAME) if (run_dir / JOURNAL_NAME).exists() else []
    contents = (
        read_feedback_log(run_dir / "feedback.jsonl") if (run_dir / "feedback.jsonl").exists() else None
    )
    events = [e for e in (contents.events if contents else []) if e.session.endswith("/browser")]
    by_seq: dict[int, list[Any]] = {}
    for e in events:
        by_seq.setdefault(e.seq, []).append(e)
    lost = 0
    matched: set[int] = set()
    at = 0
    for press in acked:
        assert press.ack is not None and press.answered_wall is not None
        want = (press.value, press.ack.get("episode"), press.ack.get("step"), bool(press.ack.get("paused")))
        found = None
        for i in range(at, len(journal)):
            j = journal[i]
            same = (j.value, j.episode, j.step, j.source == PAUSED_SOURCE) == want
            if same and press.sent_wall - WALL_SLACK_S <= j.wall <= press.answered_wall + WALL_SLACK_S:
                found = i
                break
        if found is None:
            lost += 1
            continue
        at = found + 1
        entry = journal[found]
        logged = by_seq.get(entry.n, [])
        if not logged or (logged[0].value, logged[0].source) != (entry.value, entry.source):
            lost += 1
        matched.add(entry.n)
    duplicated = sum(len(v) - 1 for v in by_seq.values()) + (contents.duplicates if contents else 0)
    journaled_ns = Counter(j.n for j in journal)
    duplicated += sum(n - 1 for n in journaled_ns.values())
    return {
        "acked": len(acked),
        "journaled": len(journal),
        "logged": len(events),
        "lost": lost,
        "duplicated": duplicated,
        "unacked_logged": len(set(by_seq) - matched),
    }
