"""The local web server of the browser trainer (aiohttp): the page, its static files and one WebSocket.

It runs in its own thread with its own event loop, so training never waits for the network. Every message
from a page is checked (``messages.parse_message``) and rate-limited; a rejected message is logged and
answered with an ``error`` message, and the connection stays open. The server binds to 127.0.0.1 by
default; any other address needs the access token, which is part of the printed URL.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import secrets
import threading
import time
from pathlib import Path
from typing import Any

from aiohttp import WSMsgType, web

from hfrl_torch.interactive.messages import MessageError, RateLimiter, parse_message
from hfrl_torch.interactive.session import TeachingSession

STATIC = Path(__file__).parent / "static"
LOG = logging.getLogger("hfrl_torch.interactive")
FRAME_POLL_S = 0.02
HARD_MAX_BYTES = 65536  # aiohttp closes a connection whose frame is larger than this


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address or ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class TeachingServer:
    """Serves the page and relays between it and a :class:`TeachingSession`.

    :param session: the shared state with the training loop.
    :param host: address to bind (127.0.0.1 by default).
    :param port: port (0: any free one).
    :param token: access token; required (and generated when None) for a non-loopback host.
    :param keys: the page's key bindings: ``good``, ``bad``, ``pause``, ``presence``.
    :param view: ``tetris`` or ``keepaway``, what the page draws.
    :param max_message_bytes: largest message accepted.
    :param max_messages_per_s: rate limit per page (bursts of twice as many).
    """

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
    ) -> None:
        if token is None and not is_loopback(host):
            token = secrets.token_urlsafe(16)
        self.session = session
        self.host = host
        self.port = port
        self.token = token
        self.keys = {"good": "/", "bad": "z", "pause": "p", "presence": "h", **(keys or {})}
        self.view = view
        self.max_message_bytes = max_message_bytes
        self.max_messages_per_s = max_messages_per_s
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    @property
    def url(self) -> str:
        """The page's address, with the token when there is one."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        query = f"?token={self.token}" if self.token else ""
        return f"http://{host}:{self.port}/{query}"

    def _authorised(self, request: web.Request) -> bool:
        return self.token is None or secrets.compare_digest(request.query.get("token", ""), self.token)

    async def _index(self, request: web.Request) -> web.StreamResponse:
        if not self._authorised(request):
            return web.Response(
                status=403, text="access token missing or wrong: use the URL train.py printed"
            )
        return web.FileResponse(STATIC / "index.html")

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        if not self._authorised(request):
            return web.Response(status=403, text="access token missing or wrong")
        ws = web.WebSocketResponse(max_msg_size=HARD_MAX_BYTES, heartbeat=20.0)
        await ws.prepare(request)
        self.session.connect()
        sender = asyncio.ensure_future(self._send_frames(ws))
        limiter = RateLimiter(self.max_messages_per_s, int(2 * self.max_messages_per_s))
        try:
            await ws.send_json({"type": "config", "keys": self.keys, "view": self.view})
            await ws.send_json(self.session.settings())
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    await self._handle(ws, msg.data, limiter)
                elif msg.type == WSMsgType.BINARY:
                    await self._reject(ws, "binary frames are not accepted; allowed: JSON text")
                elif msg.type == WSMsgType.ERROR:
                    LOG.warning("websocket closed with an error: %s", ws.exception())
        finally:
            sender.cancel()
            self.session.disconnect()
        return ws

    async def _handle(self, ws: web.WebSocketResponse, data: str, limiter: RateLimiter) -> None:
        if not limiter.allow(time.monotonic()):
            await self._reject(ws, f"too many messages; allowed: {self.max_messages_per_s:g} per second")
            return
        try:
            message = parse_message(data, self.max_message_bytes)
        except MessageError as e:
            await self._reject(ws, str(e))
            return
        self.session.apply(message)
        await ws.send_json({"type": "ack", "message": type(message).__name__.lower()})
        if type(message).__name__ != "Feedback":
            await ws.send_json(self.session.settings())

    async def _reject(self, ws: web.WebSocketResponse, why: str) -> None:
        self.session.reject()
        LOG.warning("rejected a message from the page: %s", why)
        if not ws.closed:
            await ws.send_json({"type": "error", "message": why})

    async def _send_frames(self, ws: web.WebSocketResponse) -> None:
        sent, sent_curve = -1, 0
        while not ws.closed:
            version, frame = self.session.latest()
            if version != sent:
                sent = version
                await ws.send_json(frame)
            curve_version, curve = self.session.latest_curve()
            if curve_version != sent_curve:
                sent_curve = curve_version
                await ws.send_json(curve)
            await asyncio.sleep(FRAME_POLL_S)

    def _app(self) -> web.Application:
        app = web.Application()
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_static("/static/", STATIC)
        return app

    def _serve(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)

        async def start() -> None:
            self._runner = web.AppRunner(self._app(), access_log=None)
            await self._runner.setup()
            site = web.TCPSite(self._runner, self.host, self.port)
            await site.start()
            self.port = int(self._runner.addresses[0][1])

        try:
            loop.run_until_complete(start())
        except BaseException as e:  # the port is taken, the address is not ours...
            self._error = e
            self._started.set()
            return
        self._started.set()
        loop.run_forever()
        loop.run_until_complete(self._runner.cleanup())
        loop.close()

    def start(self) -> str:
        """Start serving in a daemon thread; returns the URL. Raises OSError if the address is unusable."""
        self._thread = threading.Thread(target=self._serve, name="teaching-server", daemon=True)
        self._thread.start()
        self._started.wait(timeout=30)
        if self._error is not None:
            raise OSError(f"cannot serve the browser trainer on {self.host}:{self.port}: {self._error}")
        return self.url

    def stop(self) -> None:
        """Stop serving (open pages see the connection close)."""
        if self._loop is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=10)

    def __enter__(self) -> TeachingServer:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()
