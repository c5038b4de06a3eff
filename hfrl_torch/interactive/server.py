"""The local web server of the browser trainer (aiohttp): the page, its static files and its WebSocket.

It runs in its own thread with its own event loop, so training never waits for the network. What it lets
in (docs/security.md has the whole model):

* **Host**: every request's ``Host`` header must name this server: the bound address and port
  (``localhost`` too on loopback; on a wildcard address any IP literal, this machine's names and
  ``allowed_hosts``). A DNS name that merely points here (DNS rebinding) is refused with 400.
* **Origin**: a WebSocket must come from the page served here: ``Origin`` must be ``http://`` plus the
  request's own Host. ``null``, ``file://``, foreign and missing origins are refused with 403.
* **Token**: off loopback the page and the WebSocket need the access token of the printed URL (403
  otherwise, also for a token that is not ASCII).
* **Connections**: at most ``max_connections`` pages at once (503 beyond). The first
  ``max_teachers`` (one by default) teach; the others only watch: they get the frames, and every message
  they send is answered with an error. When a teaching page closes, the oldest watching page teaches.
* **Messages**: one rate limit for the whole session (all pages, reconnections included); every
  message is checked (``messages.parse_message``: types, bounded numbers, size); anything rejected is
  answered with an ``error`` message and the connection stays open; nothing a page sends can raise out
  of the handler.
* **Logging**: rejections are counted and logged as one line per ``rejection_log_s`` seconds at most,
  so a flood cannot grow train.log.

:meth:`TeachingServer.stop` stops taking messages, sends every open page the run's last word (``end``:
finished or stopped, and the session's summary), closes the pages, then the server: it returns within
about a second with pages open, and no message is acknowledged after it returns.
"""

from __future__ import annotations

import asyncio
import logging
import re
import secrets
import time
from collections import deque
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from aiohttp import WSCloseCode, WSMessage, WSMsgType, web

from hfrl_torch.feedback.events import FeedbackQueueClosedError, FeedbackQueueFullError
from hfrl_torch.interactive.http_guard import (
    GuardedServer,
    is_loopback,
    split_authority,
)
from hfrl_torch.interactive.messages import Feedback, MessageError, RateLimiter, parse_message, shown
from hfrl_torch.interactive.session import NotTaken, TeachingSession

STATIC = Path(__file__).parent / "static"
TAB_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")
STATIC_FILES = frozenset(p.name for p in STATIC.iterdir() if p.is_file() and p.name != "index.html")
LOG = logging.getLogger("hfrl_torch.interactive")
FRAME_POLL_S = 0.02
HARD_MAX_BYTES = 65536  # aiohttp closes a connection whose frame is larger than this
CLOSE_TIMEOUT_S = 0.5  # how long closing a page waits for its answer
STOP_TIMEOUT_S = 3.0


class TeachingServer(GuardedServer):
    """Serves the page and relays between it and a :class:`TeachingSession`.

    :param session: the shared state with the training loop.
    :param host: address to bind (127.0.0.1 by default).
    :param port: port (0: any free one).
    :param token: access token; required (and generated when None) for a non-loopback host.
    :param keys: the page's key bindings: ``good``, ``bad``, ``pause``, ``presence``.
    :param view: ``tetris`` or ``keepaway``, what the page draws.
    :param max_message_bytes: largest message accepted.
    :param max_messages_per_s: rate limit of the session, all pages together (bursts of twice as many).
    :param max_teachers: pages that may teach at once; later pages only watch.
    :param max_connections: pages open at once, teaching or watching; more are refused.
    :param max_http_connections: TCP connections open at once, pages and file requests together; one more
        is answered 503 and closed at once, so that a flood of sockets cannot use up the run's file handles.
    :param idle_timeout_s: a connection that has not sent a whole request (or stays idle between two) this
        long is closed, so that half-sent requests do not hold connections; open pages are not affected.
    :param hold_s: how long a teaching page's place is kept for its tab after it closes (a reload: the page
        sends its tab's name), before a watching page takes it (None: the session's ``reconnect_s``).
    :param allowed_hosts: more names the page may be reached by (e.g. the machine's name on the LAN).
    :param rejection_log_s: seconds between the log lines that count rejections.
    :param clock: the rate limit's clock (seconds; ``time.monotonic``).
    """

    thread_name = "teaching-server"
    serving = "the browser trainer"
    close_timeout_s = CLOSE_TIMEOUT_S
    stop_timeout_s = STOP_TIMEOUT_S

    def __init__(
        self,
        session: TeachingSession,
        host: str = "127.0.0.1",
        port: int = 8765,
        token: str | None = None,
        keys: dict[str, str] | None = None,
        view: str = "tetris",
        max_message_bytes: int = 1024,
        max_messages_per_s: float = 20.0,
        max_teachers: int = 1,
        max_connections: int = 4,
        max_http_connections: int = 64,
        idle_timeout_s: float = 10.0,
        hold_s: float | None = None,
        allowed_hosts: Iterable[str] = (),
        rejection_log_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not 1 <= max_teachers <= max_connections:
            raise ValueError(
                f"TeachingServer needs 1 <= max_teachers <= max_connections, got {max_teachers} and "
                f"{max_connections}"
            )
        if max_http_connections < max_connections:
            raise ValueError(
                f"TeachingServer needs max_http_connections >= max_connections, got {max_http_connections} "
                f"and {max_connections}"
            )
        if token is None and not is_loopback(host):
            token = secrets.token_urlsafe(16)
        super().__init__(
            host,
            port,
            allowed_hosts,
            max_http_connections,
            idle_timeout_s,
            rejection_log_s,
            what="browser trainer server",
            log=LOG,
        )
        self.session = session
        self.token = token
        self.keys = {"good": "/", "bad": "z", "pause": "p", "presence": "h", **(keys or {})}
        self.view = view
        self.max_message_bytes = max_message_bytes
        self.max_messages_per_s = max_messages_per_s
        self.max_teachers = max_teachers
        self.max_connections = max_connections
        self.clock = clock
        self._limiter = RateLimiter(max_messages_per_s, int(2 * max_messages_per_s))
        self._teachers: list[web.WebSocketResponse] = []
        self._sent: dict[web.WebSocketResponse, deque[tuple[float, int]]] = {}  # (wall, frame version)
        self._watchers: list[web.WebSocketResponse] = []
        self._open = 0
        self._closing = False
        self._background: set[asyncio.Future[bool]] = set()
        self._senders: dict[web.WebSocketResponse, asyncio.Future[None]] = {}
        self._tabs: dict[web.WebSocketResponse, str] = {}  # each page's tab name ("": none given)
        self._held: dict[str, asyncio.TimerHandle] = {}  # teaching places kept for a reloading tab
        self.hold_s = session.reconnect_s if hold_s is None else float(hold_s)

    @property
    def url(self) -> str:
        """The page's address, with the token when there is one."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        query = f"?token={self.token}" if self.token else ""
        return f"http://{host}:{self.port}/{query}"

    @property
    def teachers(self) -> int:
        """Pages teaching now."""
        return len(self._teachers)

    @property
    def watchers(self) -> int:
        """Pages only watching now."""
        return len(self._watchers)

    # --- who may connect ---

    def _token_ok(self, request: web.Request) -> bool:
        if self.token is None:
            return True
        try:
            given = request.query.get("token", "")
        except Exception:  # a query aiohttp cannot decode
            return False
        return secrets.compare_digest(given.encode("utf-8", "surrogatepass"), self.token.encode("utf-8"))

    def _origin_ok(self, origin: str | None, where: tuple[str, int] | None) -> bool:
        if origin is None or where is None:
            return False
        scheme, sep, rest = origin.partition("://")
        return bool(sep) and scheme.lower() == "http" and split_authority(rest) == where

    def _refusal(self, request: web.Request) -> web.Response | None:
        """The answer to a request that may not be served (None: it may)."""
        refusal, where = self._host_refusal(request)
        if refusal is not None:
            return refusal
        if request.path in ("/", "/ws") and not self._token_ok(request):
            return self._refuse(
                403, "bad token", "access token missing or wrong: use the URL train.py printed"
            )
        if request.path == "/ws" and not self._origin_ok(request.headers.get("Origin"), where):
            return self._refuse(
                403,
                "bad Origin",
                f"Origin {shown(request.headers.get('Origin'))} is not this page's: only the page served "
                f"here may connect",
            )
        return None

    # --- pages ---

    async def _index(self, request: web.Request) -> web.StreamResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        if self._closing:
            return self._refuse(503, "server stopping", "the training run is stopping")
        if self._open >= self.max_connections:
            return self._refuse(
                503, "too many pages", f"{self._open} pages are open; allowed: at most {self.max_connections}"
            )
        ws = web.WebSocketResponse(max_msg_size=HARD_MAX_BYTES, heartbeat=20.0, timeout=CLOSE_TIMEOUT_S)
        self._open += 1
        try:
            await ws.prepare(request)
        except BaseException:
            self._open -= 1
            raise
        tab = request.query.get("tab", "")
        tab = tab if TAB_NAME.fullmatch(tab) else ""
        teaching = self._claim(tab)
        (self._teachers if teaching else self._watchers).append(ws)
        self._tabs[ws] = tab
        self.session.connect()
        sender = asyncio.ensure_future(self._send_frames(ws))
        self._senders[ws] = sender
        try:
            config = {"type": "config", "keys": self.keys, "view": self.view, **self.session.public_info()}
            timing = {"reaction_s": self.session.reaction_s, "reconnect_s": self.session.reconnect_s}
            await self._send(ws, {**config, **timing})
            await self._send(ws, self.session.settings())
            await self._send(ws, self._role(teaching))
            async for msg in ws:
                try:
                    await self._on_message(ws, msg)
                except Exception as e:  # never lets one message drop the connection
                    self._unhandled(e)
                    await self._send(
                        ws, {"type": "error", "message": "internal error; the message was ignored"}
                    )
        finally:
            sender.cancel()
            self._senders.pop(ws, None)
            self._sent.pop(ws, None)
            self._forget(ws)
            self._open -= 1
            self.session.disconnect()
        return ws

    @staticmethod
    def _role(teaching: bool) -> dict[str, str]:
        if teaching:
            return {"type": "role", "role": "teach", "text": "connected: you are teaching"}
        return {"type": "role", "role": "watch", "text": "watching only: another page is teaching"}

    def _claim(self, tab: str) -> bool:
        """Whether a page opening in ``tab`` teaches: the tab whose teaching place is held for it does (a
        reload), otherwise the page takes a free place; a held place is not free."""
        held = self._held.pop(tab, None) if tab else None
        if held is not None:
            held.cancel()
            return True
        return len(self._teachers) + len(self._held) < self.max_teachers

    def _forget(self, ws: web.WebSocketResponse) -> None:
        tab = self._tabs.pop(ws, "")
        if ws in self._watchers:
            self._watchers.remove(ws)
        if ws in self._teachers:
            self._teachers.remove(ws)
            if tab and self.hold_s > 0 and not self._closing:  # a reload: its place waits for it
                assert self._loop is not None
                self._held[tab] = self._loop.call_later(self.hold_s, self._release, tab)
            else:
                self._promote()

    def _release(self, tab: str) -> None:
        """The teacher's tab did not come back in time: its place goes to a watching page."""
        self._held.pop(tab, None)
        self._promote()

    def _promote(self) -> None:
        while (
            self._watchers and len(self._teachers) + len(self._held) < self.max_teachers and not self._closing
        ):
            promoted = self._watchers.pop(0)
            self._teachers.append(promoted)
            task = asyncio.ensure_future(self._send(promoted, self._role(True)))
            self._background.add(task)
            task.add_done_callback(self._background.discard)

    async def _on_message(self, ws: web.WebSocketResponse, msg: WSMessage) -> None:
        if msg.type == WSMsgType.TEXT:
            await self._text(ws, msg.data)
        elif msg.type == WSMsgType.BINARY:
            await self._reject(ws, "binary", "binary frames are not accepted; allowed: JSON text")
        elif msg.type == WSMsgType.ERROR:
            self.rejections.add("connection error", f"websocket closed with an error: {ws.exception()}")

    async def _text(self, ws: web.WebSocketResponse, data: str) -> None:
        if self._closing:
            await self._reject(ws, "server stopping", "the run is stopping; nothing more is taken")
            return
        if ws not in self._teachers:
            await self._reject(
                ws, "watch-only", "this page only watches: another page is teaching (one at a time)"
            )
            return
        if not self._limiter.allow(self.clock()):
            await self._reject(
                ws, "rate limit", f"too many messages; allowed: {self.max_messages_per_s:g} per second"
            )
            return
        try:
            message = parse_message(data, self.max_message_bytes)
        except MessageError as e:
            await self._reject(ws, "invalid", str(e))
            return
        at = self.session.clock()
        try:
            reply = self.session.apply(message, self._on_screen(ws, at - self.session.reaction_s), at)
        except (NotTaken, FeedbackQueueFullError, FeedbackQueueClosedError) as e:
            press = message.id if isinstance(message, Feedback) else -1
            await self._reject(ws, "not taken", f"not taken: {e}", id=press)
            return
        await self._send(ws, {"type": "ack", "message": type(message).__name__.lower(), **reply})
        # the new settings reach every page through its own sender (within FRAME_POLL_S): a page that stops
        # reading blocks only its sender, never this handler and the teacher's next acknowledgement

    def _on_screen(self, ws: web.WebSocketResponse, wall: float) -> int:
        """The version of the last frame sent to ``ws`` at or before ``wall`` (-1: none)."""
        for sent, version in reversed(self._sent.get(ws, ())):
            if sent <= wall:
                return version
        return -1

    async def _reject(self, ws: web.WebSocketResponse, kind: str, why: str, **extra: Any) -> None:
        self.session.reject()
        self.rejections.add(kind, why)
        await self._send(ws, {"type": "error", "message": why, **extra})

    @staticmethod
    async def _send(ws: web.WebSocketResponse, obj: dict[str, Any]) -> bool:
        """Send ``obj``; False (and nothing raised) if the page has gone."""
        if ws.closed:
            return False
        try:
            await ws.send_json(obj)
        except (ConnectionError, RuntimeError):  # closing under us
            return False
        return True

    async def _send_frames(self, ws: web.WebSocketResponse) -> None:
        sent, sent_curve, sent_settings = -1, 0, self.session.settings_key()
        shown = self._sent.setdefault(ws, deque(maxlen=1000))
        while not ws.closed:
            settings = self.session.settings_key()
            if settings != sent_settings:
                sent_settings = settings
                if not await self._send(ws, self.session.settings()):
                    return
            version, frame = self.session.latest()
            if version != sent:
                sent = version
                shown.append((self.session.clock(), version))
                if not await self._send(ws, frame):
                    return
            curve_version, curve = self.session.latest_curve()
            if curve_version != sent_curve:
                sent_curve = curve_version
                if not await self._send(ws, curve):
                    return
            await asyncio.sleep(FRAME_POLL_S)

    # --- running ---

    def _app(self) -> web.Application:
        app = self._guarded_app()
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/static/{name}", self._static)
        return app

    async def _static(self, request: web.Request) -> web.StreamResponse:
        """One of the page's own files, by name from a fixed list: any other name (a long one included, which
        the file system would refuse with an error) is a plain 404, and no path leaves the folder."""
        name = request.match_info["name"]
        if name not in STATIC_FILES:
            return web.Response(status=404, text="not found")
        return web.FileResponse(STATIC / name)

    async def _shutdown(self, final: Callable[[], dict[str, Any]] | None = None) -> None:
        """Stop taking messages, tell every page ``final()``, close them, then the server."""
        self._closing = True
        for sender in self._senders.values():  # the end message is the last each page gets
            sender.cancel()
        await asyncio.gather(*self._senders.values(), return_exceptions=True)
        pages = [*self._teachers, *self._watchers]
        if final is not None:
            last = final()  # after the last acknowledgement: its counts are the run's
            sends = (
                asyncio.wait_for(self._send(ws, last), CLOSE_TIMEOUT_S) for ws in pages
            )  # a stalled page
            await asyncio.gather(*sends, return_exceptions=True)
        await asyncio.gather(
            *(ws.close(code=WSCloseCode.GOING_AWAY, message=b"the training run stopped") for ws in pages),
            return_exceptions=True,
        )
        await self._close_listener()

    def stop(self, final: Callable[[], dict[str, Any]] | None = None) -> None:
        """Stop taking messages, send ``final()`` (the run's last word, e.g. the session's summary) to every
        open page, close them, then stop serving; idempotent. Call it from another thread than the
        server's: once it returns, no message is acknowledged any more."""
        self._stop_loop(lambda: self._shutdown(final))
