"""The study's web server (aiohttp): the participants' pages and API, the teaching page's proxy to each
participant's own run, and the researcher's page.

One server hosts the whole study (docs/study.md). It runs in its own thread and event loop; every call
into the :class:`~hfrl_torch.study.manager.Study` (which writes files and starts processes) goes through
one worker thread, so the network never waits on the disk and the study sees one caller at a time. What it
lets in, besides :class:`~hfrl_torch.interactive.http_guard.GuardedServer`'s Host check, framing headers,
connection cap and idle timeout:

* **Participants**: ``/p/<code>/...`` opens the participant of that code alone; an unknown code is 404
  (and unknown codes are rate limited, so codes cannot be guessed quickly). No answer names the
  participant's condition, and the join request takes no say in it.
* **Bodies**: at most ``MAX_BODY_BYTES``, JSON within :func:`~hfrl_torch.common.bounded_json.loads_bounded`'s
  bounds, each field checked; anything else is 400 (413 for size). One rate limit per participant (429).
* **WebSockets**: ``/p/<code>/teach/ws`` must come from a page served here (``Origin`` is ``http://`` or
  ``https://`` plus the request's own Host); it is relayed frame by frame, each direction in its own task,
  to the participant's worker (``ws://127.0.0.1:<port>/ws?token=...``), whose own server checks every
  message. A page that stops reading holds up only its own relay.
* **Researcher**: ``/admin...`` needs the researcher token (``?token=`` or ``Authorization: Bearer``),
  compared in constant time; 403 otherwise.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import io
import json
import logging
import math
import queue
import re
import secrets
import threading
import time
import zipfile
from collections import Counter
from collections.abc import Callable, Coroutine, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import aiohttp
from aiohttp import WSCloseCode, WSMsgType, web

from hfrl_torch.common.bounded_json import JSONBoundsError, loads_bounded
from hfrl_torch.common.errors import UserError
from hfrl_torch.interactive.http_guard import GuardedServer, split_authority
from hfrl_torch.interactive.messages import RateLimiter, shown
from hfrl_torch.interactive.server import HARD_MAX_BYTES, TAB_NAME
from hfrl_torch.interactive.server import STATIC as TEACH_STATIC
from hfrl_torch.interactive.server import STATIC_FILES as TEACH_FILES
from hfrl_torch.study import layout
from hfrl_torch.study.manager import StepConflict, Study

LOG = logging.getLogger("hfrl_torch.study")
STATIC = Path(__file__).parent / "static"
STUDY_FILES = frozenset(p.name for p in STATIC.iterdir() if p.is_file() and p.suffix != ".html")
CODE = re.compile(r"[A-Za-z0-9-]{1,64}")  # what may be a code; the study decides whether it is one
MAX_BODY_BYTES = 32768
CLOSE_TIMEOUT_S = 0.5
STOP_TIMEOUT_S = 5.0
WORKER_CONNECT_S = 10.0  # a run that does not answer the handshake in this long: the page tries again
# what a participant's page may see of the study's state: never the condition, the run's paths or commands
PARTICIPANT_FIELDS = ("step", "study", "teaching", "stopped", "ended", "summary")
SUMMARY_HIDDEN = ("run_dir", "feedback_log", "summary_file", "resume")
BEFORE_TEACHING = ("consent", "instructions", "practice", "calibration")
# the close codes the teaching page's proxy uses (app.js shows the reason): try again soon, or it is over
WAIT, OVER = 4000, 4001
CONFIG_PREFIX = '{"type": "config"'  # how TeachingServer's opening message starts (json.dumps' spacing)


class _Bad(Exception):
    """A request refused with ``status`` and a one-line reason (answered as JSON ``{"error": why}``)."""

    def __init__(self, status: int, kind: str, why: str) -> None:
        super().__init__(why)
        self.status = status
        self.kind = kind


def finite(value: Any) -> Any:
    """``value`` with every NaN or infinity replaced by None (a run's metrics hold NaN, which JSON, and so a
    browser's ``response.json()``, does not take)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite(v) for v in value]
    return value


def json_response(value: Any, status: int = 200) -> web.Response:
    """A JSON answer that a browser can parse (see :func:`finite`)."""
    return web.json_response(
        finite(value), status=status, dumps=functools.partial(json.dumps, allow_nan=False)
    )


def participant_view(state: dict[str, Any]) -> dict[str, Any]:
    """What of a participant's state their page gets: the fields of :data:`PARTICIPANT_FIELDS` only, and
    the teaching summary without the run's paths and resume command (the study keeps those)."""
    view = {k: state[k] for k in PARTICIPANT_FIELDS if k in state}
    summary = view.get("summary")
    if isinstance(summary, dict):
        view["summary"] = {k: v for k, v in summary.items() if k not in SUMMARY_HIDDEN}
        if "checkpoint" in summary:
            view["summary"]["checkpoint"] = bool(summary["checkpoint"])
    return view


def blinded(text: str) -> str:
    """A message of the run for a participant's page: the run's opening ``config`` without its
    ``weight_sentence``, which names the condition's fusion (and the thesis's equations); anything else as
    it is (only the opening message is parsed)."""
    if not text.startswith(CONFIG_PREFIX):
        return text
    try:
        message = json.loads(text)
    except ValueError:
        return text
    if not isinstance(message, dict) or message.get("type") != "config":
        return text
    message.pop("weight_sentence", None)
    return json.dumps(message)


class _ChunkQueue(io.RawIOBase):
    """A write-only file that hands what is written to a bounded queue (the zip is made in a thread and
    streamed as it is made)."""

    def __init__(self, chunks: queue.Queue[bytes | None]) -> None:
        self.chunks = chunks
        self.written = 0

    def writable(self) -> bool:
        return True

    def write(self, b: Any) -> int:
        data = bytes(b)
        self.chunks.put(data)
        self.written += len(data)
        return len(data)


def data_files(directory: Path) -> Iterator[Path]:
    """The study directory's files that the researcher's download holds: all but the researcher token and
    the participant code list."""
    for path in sorted(directory.rglob("*")):
        if path.is_file() and not path.is_symlink() and path.name not in layout.SECRETS:
            yield path


class StudyServer(GuardedServer):
    """Serves a :class:`~hfrl_torch.study.manager.Study`: participants' pages, their API, the teaching
    proxy and the researcher's page; calls ``study.poll()`` every ``poll_s`` seconds.

    :param study: the open study.
    :param directory: what ``/admin/data.zip`` holds (None: the study's directory).
    :param host: address to bind; anything but loopback belongs behind a TLS proxy (docs/study.md).
    :param port: port (0: any free one).
    :param allowed_hosts: the proxy's public names: a request naming one is served whatever its port.
    :param max_http_connections: TCP connections at once, every participant's page and file requests.
    :param idle_timeout_s: half-sent or idle HTTP connections are closed after this long.
    :param max_pages_per_participant: teaching pages open at once per participant.
    :param max_requests_per_s: API requests per second per participant (bursts of twice as many).
    :param max_joins_per_s: new participants per second, all together (bursts of five times as many).
    :param max_misses_per_s: requests naming an unknown code per second, all together (guessing codes).
    :param poll_s: seconds between two ``study.poll()``.
    :param rejection_log_s: seconds between the log lines that count rejections.
    :param clock: the rate limits' clock.
    """

    busy_text = b"too many connections to the study; try again shortly"
    thread_name = "study-server"
    serving = "the study"
    close_timeout_s = CLOSE_TIMEOUT_S
    stop_timeout_s = STOP_TIMEOUT_S

    def __init__(
        self,
        study: Study,
        directory: Path | None = None,
        host: str = "127.0.0.1",
        port: int = 8800,
        allowed_hosts: tuple[str, ...] | list[str] = (),
        max_http_connections: int = 512,
        idle_timeout_s: float = 10.0,
        max_pages_per_participant: int = 4,
        max_requests_per_s: float = 10.0,
        max_joins_per_s: float = 2.0,
        max_misses_per_s: float = 5.0,
        poll_s: float = 0.5,
        rejection_log_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(
            host,
            port,
            allowed_hosts,
            max_http_connections,
            idle_timeout_s,
            rejection_log_s,
            what="study server",
            log=LOG,
        )
        if max_pages_per_participant < 1 or not poll_s > 0:
            raise ValueError(
                f"StudyServer needs max_pages_per_participant >= 1 and poll_s > 0, got "
                f"{max_pages_per_participant!r} and {poll_s!r}"
            )
        self.study = study
        self.directory = Path(study.directory if directory is None else directory)
        self.max_pages_per_participant = max_pages_per_participant
        self.max_requests_per_s = max_requests_per_s
        self.poll_s = poll_s
        self.clock = clock
        self._joins = RateLimiter(max_joins_per_s, max(1, int(5 * max_joins_per_s)))
        self._misses = RateLimiter(max_misses_per_s, max(1, int(4 * max_misses_per_s)))
        self._limits: dict[str, RateLimiter] = {}
        self._pages: Counter[str] = Counter()
        self._sockets: set[web.WebSocketResponse] = set()
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="study-calls")
        self._client: aiohttp.ClientSession | None = None
        self._closing = False
        self.polls = 0

    # --- addresses ---

    def _base(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}/"

    @property
    def url(self) -> str:
        """The study's link for participants."""
        return self._base()

    @property
    def researcher_url(self) -> str:
        """The researcher's page, with the token."""
        return f"{self._base()}admin?{urlencode({'token': self.study.researcher_token})}"

    # --- who may connect ---

    def _host_ok(self, where: tuple[str, int] | None) -> bool:
        """This server's names at its port, or one of ``allowed_hosts`` at any port (behind a proxy the
        Host is the proxy's public name and port)."""
        if where is not None and where[0] in self.allowed_hosts:
            return True
        return super()._host_ok(where)

    @staticmethod
    def _origin_ok(origin: str | None, host: str | None) -> bool:
        """Whether a WebSocket's ``Origin`` is a page served here: ``http://`` or ``https://`` (behind a TLS
        proxy) plus the request's own Host."""
        if origin is None or host is None:
            return False
        scheme, sep, rest = origin.partition("://")
        where = split_authority(host)
        return (
            bool(sep)
            and scheme.lower() in ("http", "https")
            and where is not None
            and (split_authority(rest) == where)
        )

    def _researcher(self, request: web.Request) -> bool:
        try:
            given = request.query.get("token", "")
        except Exception:  # a query aiohttp cannot decode
            return False
        header = request.headers.get("Authorization", "")
        if not given and header[:7].lower() == "bearer ":
            given = header[7:].strip()
        expected = self.study.researcher_token.encode("utf-8")
        return bool(given) and secrets.compare_digest(given.encode("utf-8", "surrogatepass"), expected)

    def _refusal(self, request: web.Request) -> web.Response | None:
        refusal, _ = self._host_refusal(request)
        if refusal is not None:
            return refusal
        path = request.path
        if (path == "/admin" or path.startswith("/admin/")) and not self._researcher(request):
            return self._refuse(
                403, "bad token", "researcher token missing or wrong: use the link study.py printed"
            )
        if path.endswith("/teach/ws") and not self._origin_ok(
            request.headers.get("Origin"), request.headers.get("Host")
        ):
            return self._refuse(
                403,
                "bad Origin",
                f"Origin {shown(request.headers.get('Origin'))} is not this study's page: only the page "
                "served here may connect",
            )
        return None

    # --- helpers ---

    async def _call(self, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` on the study's one worker thread."""
        return await asyncio.get_running_loop().run_in_executor(self._executor, fn, *args)

    def _bad(self, error: _Bad) -> web.Response:
        self.rejections.add(error.kind, str(error))
        return json_response({"error": str(error)}, status=error.status)

    async def _code(self, request: web.Request, limited: bool = False) -> str:
        """The request's participant code, if a participant has it (else a 404, or 429 when unknown codes
        come too fast); with ``limited``, the participant's own rate limit is taken."""
        given = request.match_info["code"]
        now = self.clock()
        participant = await self._call(self.study.get, given) if CODE.fullmatch(given) else None
        if participant is None:
            if not self._misses.allow(now):
                raise _Bad(429, "unknown codes too fast", "too many unknown codes; wait a minute")
            raise _Bad(404, "unknown code", f"no participant has the code {shown(given, 20)}")
        code = participant.code
        if limited:
            limit = self._limits.get(code)
            if limit is None:
                limit = RateLimiter(self.max_requests_per_s, int(2 * self.max_requests_per_s))
                self._limits[code] = limit
            if not limit.allow(now):
                raise _Bad(
                    429, "rate limit", f"too many requests; allowed: {self.max_requests_per_s:g} per second"
                )
        return code

    async def _body(self, request: web.Request) -> dict[str, Any]:
        """The request's JSON object, read within :data:`MAX_BODY_BYTES` and the bounded parser's limits."""
        if request.content_length is not None and request.content_length > MAX_BODY_BYTES:
            size = request.content_length
            raise _Bad(413, "too large", f"a body of {size} bytes; allowed: at most {MAX_BODY_BYTES}")
        chunks, size = [], 0
        while True:
            chunk = await request.content.read(MAX_BODY_BYTES + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
            if size > MAX_BODY_BYTES:
                raise _Bad(413, "too large", f"a body over {MAX_BODY_BYTES} bytes; allowed: {MAX_BODY_BYTES}")
        try:
            body = loads_bounded(b"".join(chunks), max_depth=6, max_int_digits=9, max_number_chars=32)
        except JSONBoundsError as e:
            raise _Bad(400, "invalid", f"the body is not valid: {e}") from None
        if not isinstance(body, dict):
            raise _Bad(400, "invalid", f"the body must be a JSON object, got {type(body).__name__}")
        return body

    # --- participants ---

    async def _landing(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "study.html")

    async def _static(self, request: web.Request) -> web.StreamResponse:
        """One of the study page's own files, by name from a fixed list (anything else: 404)."""
        name = request.match_info["name"]
        if name not in STUDY_FILES:
            return web.Response(status=404, text="not found")
        return web.FileResponse(STATIC / name)

    async def _join(self, request: web.Request) -> web.StreamResponse:
        try:
            body = await self._body(request)
            simulated = body.get("simulated", False)  # any other field (a condition...) is ignored
            if not isinstance(simulated, bool):
                raise _Bad(400, "invalid", f"simulated={shown(simulated)} is invalid; allowed: true or false")
            if not self._joins.allow(self.clock()):
                raise _Bad(429, "joins too fast", "too many people are joining at once; try again shortly")
            try:
                participant = await self._call(self.study.join, simulated)
            except (UserError, ValueError) as e:
                why = str(e).splitlines()[0] if str(e) else "joining is closed"
                raise _Bad(403, "join refused", why) from None
        except _Bad as e:
            return self._bad(e)
        return json_response({"code": participant.code})

    async def _page(self, request: web.Request) -> web.StreamResponse:
        try:
            await self._code(request)
        except _Bad as e:
            return self._bad(e)
        return web.FileResponse(STATIC / "study.html")

    async def _page_static(self, request: web.Request) -> web.StreamResponse:
        try:
            await self._code(request)
        except _Bad as e:
            return self._bad(e)
        return await self._static(request)

    @staticmethod
    async def _slash(request: web.Request) -> web.StreamResponse:
        """``/p/<code>`` and ``/p/<code>/teach`` without their slash: redirected relatively (the page's own
        relative links need it, and so does a proxy that serves the study under a path)."""
        raise web.HTTPFound(request.path.rsplit("/", 1)[-1] + "/")

    async def _state(self, request: web.Request) -> web.StreamResponse:
        try:
            code = await self._code(request, limited=True)
        except _Bad as e:
            return self._bad(e)
        return json_response(participant_view(await self._call(self.study.state, code)))

    async def _step(self, request: web.Request) -> web.StreamResponse:
        try:
            code = await self._code(request, limited=True)
            body = await self._body(request)
            step, action, data = body.get("step"), body.get("action"), body.get("data", {})
            if not isinstance(step, str) or not isinstance(action, str) or not isinstance(data, dict):
                raise _Bad(
                    400,
                    "invalid",
                    f"step={shown(step)}, action={shown(action)}, data={shown(data)}: allowed: a step's "
                    "name, an action's name and an object",
                )
            try:
                state = await self._call(self.study.advance, code, step, action, data)
            except StepConflict as e:
                self.rejections.add("stale step", f"{code}: {shown(step)} is not the current step")
                return json_response(participant_view(e.state), status=409)
            except (UserError, ValueError) as e:
                raise _Bad(400, "invalid", str(e).splitlines()[0] if str(e) else "invalid step") from None
        except _Bad as e:
            return self._bad(e)
        return json_response(participant_view(state))

    async def _teach_page(self, request: web.Request) -> web.StreamResponse:
        try:
            await self._code(request)
        except _Bad as e:
            return self._bad(e)
        return web.FileResponse(TEACH_STATIC / "index.html")

    async def _teach_static(self, request: web.Request) -> web.StreamResponse:
        try:
            await self._code(request)
        except _Bad as e:
            return self._bad(e)
        name = request.match_info["name"]
        if name not in TEACH_FILES:
            return web.Response(status=404, text="not found")
        return web.FileResponse(TEACH_STATIC / name)

    # --- the teaching page's WebSocket, relayed to the participant's worker ---

    async def _unavailable(self, code: str) -> tuple[int, str]:
        """The close code and the page's words when the participant's run cannot be reached now."""
        state = await self._call(self.study.state, code)
        step = state.get("step")
        if state.get("stopped"):
            return WAIT, "The researcher has paused this session. This page goes on when they resume it."
        if step == "teaching":
            return WAIT, "The run is starting: the game appears here in a moment."
        if step in BEFORE_TEACHING:
            return OVER, "Teaching has not started yet: go back to the study page to continue."
        return OVER, "The teaching session has ended: go back to the study page to continue."

    async def _teach_ws(self, request: web.Request) -> web.StreamResponse:
        try:
            code = await self._code(request)
        except _Bad as e:
            return self._bad(e)
        if self._closing:
            return self._refuse(503, "server stopping", "the study server is stopping")
        if self._pages[code] >= self.max_pages_per_participant:
            return self._refuse(
                503,
                "too many pages",
                f"{self._pages[code]} teaching pages are open; allowed: {self.max_pages_per_participant}",
            )
        page = web.WebSocketResponse(max_msg_size=HARD_MAX_BYTES, heartbeat=20.0, timeout=CLOSE_TIMEOUT_S)
        self._pages[code] += 1
        try:
            await page.prepare(request)
            self._sockets.add(page)
            endpoint = await self._call(self.study.teaching_endpoint, code)
            if endpoint is None:
                close, why = await self._unavailable(code)
                await page.close(code=close, message=why.encode())
                return page
            port, token = endpoint
            tab = request.query.get("tab", "")
            query = urlencode({"token": token, "tab": tab if TAB_NAME.fullmatch(tab) else ""})
            assert self._client is not None
            try:
                worker = await asyncio.wait_for(
                    self._client.ws_connect(
                        f"ws://127.0.0.1:{int(port)}/ws?{query}",
                        origin=f"http://127.0.0.1:{int(port)}",
                        max_msg_size=HARD_MAX_BYTES,
                        timeout=aiohttp.ClientWSTimeout(ws_close=CLOSE_TIMEOUT_S),
                    ),
                    WORKER_CONNECT_S,
                )
            except (aiohttp.ClientError, OSError, asyncio.TimeoutError):
                await page.close(code=WAIT, message=b"The run is not answering yet: this page tries again.")
                return page
            await self._relay(page, worker)
        finally:
            self._sockets.discard(page)
            self._pages[code] -= 1
            if self._pages[code] <= 0:
                del self._pages[code]
        return page

    @staticmethod
    async def _pump(source: Any, sink: Any, text: Callable[[str], str] = str) -> None:
        """Copy frames from ``source`` to ``sink`` (text frames through ``text``) until either closes."""
        async for msg in source:
            try:
                if msg.type == WSMsgType.TEXT:
                    await sink.send_str(text(msg.data))
                elif msg.type == WSMsgType.BINARY:
                    await sink.send_bytes(msg.data)
                else:
                    return
            except (ConnectionError, RuntimeError):  # the sink is closing
                return

    async def _relay(self, page: web.WebSocketResponse, worker: aiohttp.ClientWebSocketResponse) -> None:
        """Relay both ways, each direction in its own task: a page that stops reading stalls only the frames
        to itself, never its presses nor anyone else. When the run's side closes, the page is closed with a
        reason it shows; when the page closes, so does its connection to the run."""
        up = asyncio.ensure_future(self._pump(page, worker))
        down = asyncio.ensure_future(self._pump(worker, page, blinded))
        try:
            await asyncio.wait({up, down}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (up, down):
                task.cancel()
            await asyncio.gather(up, down, return_exceptions=True)
        with contextlib.suppress(Exception):
            await asyncio.wait_for(worker.close(), CLOSE_TIMEOUT_S)
        if not page.closed:
            why = b"The run stopped. This page reconnects if it goes on."
            with contextlib.suppress(Exception):
                await asyncio.wait_for(page.close(code=WAIT, message=why), CLOSE_TIMEOUT_S)

    # --- the researcher ---

    async def _admin(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "admin.html")

    async def _participants(self, request: web.Request) -> web.StreamResponse:
        return json_response(await self._call(self.study.overview))

    async def _control(self, request: web.Request) -> web.StreamResponse:
        try:
            code = await self._code(request)
        except _Bad as e:
            return self._bad(e)
        action = request.match_info["action"]
        await self._call(self.study.stop if action == "stop" else self.study.resume, code)
        return json_response({"code": code, "done": action})

    def _zip_into(self, chunks: queue.Queue[bytes | None], cancelled: threading.Event) -> None:
        """Write the study directory's zip into ``chunks`` (None last), file by file."""
        try:
            with zipfile.ZipFile(_ChunkQueue(chunks), "w", zipfile.ZIP_DEFLATED) as archive:
                for path in data_files(self.directory):
                    if cancelled.is_set():
                        return
                    with contextlib.suppress(OSError):  # a file that went away meanwhile
                        archive.write(path, path.relative_to(self.directory).as_posix())
        finally:
            chunks.put(None)

    async def _data(self, request: web.Request) -> web.StreamResponse:
        response = web.StreamResponse(
            headers={
                "Content-Type": "application/zip",
                "Content-Disposition": f'attachment; filename="{self.directory.name or "study"}.zip"',
            }
        )
        await response.prepare(request)
        chunks: queue.Queue[bytes | None] = queue.Queue(maxsize=16)
        cancelled = threading.Event()
        loop = asyncio.get_running_loop()
        maker = loop.run_in_executor(None, self._zip_into, chunks, cancelled)
        try:
            while (chunk := await loop.run_in_executor(None, chunks.get)) is not None:
                await response.write(chunk)
            await response.write_eof()
        except ConnectionError:  # the researcher's browser went away
            pass
        finally:
            cancelled.set()
            while not maker.done():  # let the maker finish its file and see the flag
                with contextlib.suppress(queue.Empty):
                    chunks.get_nowait()
                await asyncio.sleep(0.01)
        return response

    # --- running ---

    def _app(self) -> web.Application:
        app = self._guarded_app(client_max_size=MAX_BODY_BYTES)
        r = app.router
        r.add_get("/", self._landing)
        r.add_get("/static/{name}", self._static)
        r.add_post("/api/join", self._join)
        r.add_get("/p/{code}", self._slash)
        r.add_get("/p/{code}/", self._page)
        r.add_get("/p/{code}/static/{name}", self._page_static)
        r.add_get("/p/{code}/api/state", self._state)
        r.add_post("/p/{code}/api/step", self._step)
        r.add_get("/p/{code}/teach", self._slash)
        r.add_get("/p/{code}/teach/", self._teach_page)
        r.add_get("/p/{code}/teach/static/{name}", self._teach_static)
        r.add_get("/p/{code}/teach/ws", self._teach_ws)
        r.add_get("/admin", self._admin)
        r.add_get("/admin/api/participants", self._participants)
        r.add_post("/admin/api/participants/{code}/{action:stop|resume}", self._control)
        r.add_get("/admin/data.zip", self._data)
        return app

    async def _poll(self) -> None:
        while True:
            await asyncio.sleep(self.poll_s)
            try:
                await self._call(self.study.poll)
                self.polls += 1
            except Exception as e:  # a bug in the study: counted and logged once, and polling goes on
                self._unhandled(e)

    async def _setup(self) -> None:
        self._client = aiohttp.ClientSession()

    def _tasks(self) -> list[Coroutine[Any, Any, None]]:
        return [*super()._tasks(), self._poll()]

    async def _teardown(self) -> None:
        if self._client is not None:
            await self._client.close()

    async def _shutdown(self) -> None:
        """Stop taking pages, close the open ones (saying why), then the server."""
        self._closing = True
        await asyncio.gather(
            *(
                ws.close(code=WSCloseCode.GOING_AWAY, message=b"The study server is stopping.")
                for ws in list(self._sockets)
            ),
            return_exceptions=True,
        )
        await self._close_listener()

    def stop(self) -> None:
        """Close every page and stop serving (idempotent); the study itself is the caller's to close."""
        super().stop()
        self._executor.shutdown(wait=True, cancel_futures=True)
