"""What the package's web servers (the browser trainer's and the study's) do to every request they take.

:class:`GuardedServer` holds the parts both share (docs/security.md has the whole model): the Host check
against DNS rebinding, the headers that forbid framing on every response (refusals included), a cap on open
TCP connections (one more is answered 503 and closed at once, so a flood of sockets cannot use up the
process's file handles), the idle timeout that closes half-sent requests, rejections counted and logged as
one line per interval at most, and a middleware through which no exception of a handler reaches aiohttp: a
bug is answered 500 without a traceback, counted in ``errors`` and logged once. It also runs the server in a
daemon thread with its own event loop (:meth:`GuardedServer.start`, :meth:`GuardedServer.stop`), so the
caller never waits on the network.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Awaitable, Callable, Coroutine, Iterable
from typing import Any, TypeVar

from aiohttp import web

from hfrl_torch.interactive.messages import shown

LOG = logging.getLogger("hfrl_torch.interactive")

# on every response: no other site may frame the page (a framed page is served from here, so its WebSocket
# passes the Origin check, and a decoy over it could click Good, Bad or Finish and save: clickjacking); no
# content sniffing; and the token in the page's URL never leaves in a Referer header
SECURITY_HEADERS = {
    "X-Frame-Options": "DENY",
    "Content-Security-Policy": "frame-ancestors 'none'",
    "X-Content-Type-Options": "nosniff",
    "Referrer-Policy": "no-referrer",
}
_Server = TypeVar("_Server", bound="GuardedServer")


def is_loopback(host: str) -> bool:
    """Whether ``host`` is a loopback address or ``localhost``."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def is_wildcard(host: str) -> bool:
    """Whether binding ``host`` listens on every address of the machine."""
    return host in ("", "0.0.0.0", "::")


def is_ip(name: str) -> bool:
    """Whether ``name`` is an IP literal (v4 or v6, without brackets)."""
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def split_authority(value: str, default_port: int = 80) -> tuple[str, int] | None:
    """``(host, port)`` of a Host header or an origin's ``host[:port]`` (host lower-case, IPv6 without
    brackets); None if it is malformed."""
    value = value.strip().lower()
    if not value or not value.isascii() or any(c in value for c in "/?#@ \t\\"):
        return None
    if value.startswith("["):
        end = value.find("]")
        name, rest = value[1:end], value[end + 1 :]
        if end < 0 or not is_ip(name):
            return None
    else:
        name, sep, port = value.rpartition(":")
        name, rest = (name, f":{port}") if sep else (value, "")
        if not name or ":" in name:
            return None
    if not rest:
        return name, default_port
    digits = rest[1:]
    if not (rest.startswith(":") and digits.isdigit() and 1 <= len(digits) <= 5 and int(digits) <= 65535):
        return None
    return name, int(digits)


class RejectionLog:
    """Counts what was refused, by kind, and logs it as one line per ``interval`` seconds at most."""

    def __init__(
        self, interval: float = 10.0, clock: Callable[[], float] = time.monotonic, log: logging.Logger = LOG
    ) -> None:
        self.interval = interval
        self.clock = clock
        self.log = log
        self.counts: Counter[str] = Counter()
        self.examples: dict[str, str] = {}
        self.total = 0
        self.lines = 0
        self._since = clock()

    def add(self, kind: str, why: str) -> None:
        """Count one refusal of ``kind``; the first ``why`` of each kind is kept as its example."""
        self.counts[kind] += 1
        self.examples.setdefault(kind, why if len(why) <= 160 else why[:157] + "...")
        self.total += 1

    def flush(self) -> str | None:
        """Log (one warning) and forget what was counted since the last flush; returns the line."""
        now = self.clock()
        if not self.counts:
            self._since = now
            return None
        n = sum(self.counts.values())
        parts = [f"{c} {kind} (e.g. {self.examples[kind]})" for kind, c in self.counts.most_common()]
        line = f"refused {n} requests or messages from pages in {now - self._since:.1f} s: " + "; ".join(
            parts
        )
        self.log.warning("%s", line)
        self.counts.clear()
        self.examples.clear()
        self.lines += 1
        self._since = now
        return line


class _CountingLogger(logging.Logger):
    """aiohttp's server logger: what it would log (malformed requests, mostly) is counted instead."""

    def __init__(self, server: GuardedServer) -> None:
        super().__init__(f"{server.log.name}.http")
        self.server = server

    def _log(self, level: int, msg: object, args: Any, exc_info: Any = None, **kwargs: Any) -> None:
        text = str(msg) % args if args else str(msg)
        error = exc_info[1] if isinstance(exc_info, tuple) else exc_info
        if isinstance(error, BaseException):
            text += f": {type(error).__name__}: {' '.join(str(error).split())}"
        if text.startswith("Unhandled exception"):
            self.server._unhandled(error if isinstance(error, BaseException) else RuntimeError(text))
        else:
            self.server.rejections.add("bad HTTP request", text)


class _Refused(asyncio.Protocol):
    """A connection past the cap: answered 503 (with the framing headers) and closed, so its file handle is
    free again at once."""

    def __init__(self, body: bytes) -> None:
        self.body = body

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        headers = "".join(f"{k}: {v}\r\n" for k, v in SECURITY_HEADERS.items())
        head = (
            f"HTTP/1.1 503 Service Unavailable\r\nContent-Length: {len(self.body)}\r\n{headers}"
            "Connection: close\r\n\r\n"
        )
        assert isinstance(transport, asyncio.WriteTransport)
        transport.write(head.encode() + self.body)
        transport.close()


class GuardedServer:
    """The checks and limits an aiohttp server of the package shares (see the module docstring).

    A subclass answers :meth:`_refusal` (its own token and Origin rules after :meth:`_host_refusal`), builds
    its ``web.Application`` in :meth:`_app` with :meth:`_guarded_app`, gives its :attr:`url`, and closes its
    pages in :meth:`_shutdown`; :meth:`start` serves it in a thread of its own until :meth:`stop`.

    :param host: address to bind.
    :param port: port (0: any free one; the bound one after :meth:`_listen`).
    :param allowed_hosts: more names the server may be reached by (a proxy's public name, the machine's name).
    :param max_http_connections: TCP connections open at once; one more is answered 503 and closed.
    :param idle_timeout_s: a connection that has not sent a whole request (or idles between two) this long
        is closed; open WebSockets are not affected.
    :param rejection_log_s: seconds between the log lines that count rejections.
    :param what: the server's name in its one error log line.
    :param log: where rejections and the first unexpected error are logged.
    """

    busy_text = b"too many connections to the training run's page; try again shortly"
    thread_name = "guarded-server"
    serving = "the server"  # in start's error: "cannot serve <serving> on host:port"
    close_timeout_s = 0.5  # how long closing a connection waits for its answer
    stop_timeout_s = 3.0  # how long stop waits for the shutdown, then for the thread

    def __init__(
        self,
        host: str,
        port: int,
        allowed_hosts: Iterable[str],
        max_http_connections: int,
        idle_timeout_s: float,
        rejection_log_s: float,
        what: str,
        log: logging.Logger = LOG,
    ) -> None:
        if not idle_timeout_s > 0:
            raise ValueError(f"{type(self).__name__} idle_timeout_s must be > 0, got {idle_timeout_s!r}")
        if not rejection_log_s > 0:
            raise ValueError(f"{type(self).__name__} rejection_log_s must be > 0, got {rejection_log_s!r}")
        self.host = host
        self.port = port
        self.allowed_hosts = {h.strip().lower().strip("[]") for h in allowed_hosts}
        self.max_http_connections = max_http_connections
        self.idle_timeout_s = float(idle_timeout_s)
        self.log = log
        self.what = what
        self.rejections = RejectionLog(rejection_log_s, log=log)
        self.errors = 0  # exceptions caught that a request or message caused (a bug if ever > 0)
        self._hosts: set[str] = set()
        self._runner: web.AppRunner | None = None
        self._listener: asyncio.Server | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._started = threading.Event()
        self._error: BaseException | None = None

    # --- who may connect ---

    def _names(self) -> set[str]:
        names = {self.host.lower().strip("[]"), *self.allowed_hosts}
        if is_loopback(self.host):
            names.add("localhost")
        if is_wildcard(self.host):
            names |= {"localhost", socket.gethostname().lower(), socket.getfqdn().lower()}
        return names

    def _host_ok(self, where: tuple[str, int] | None) -> bool:
        if where is None or where[1] != self.port:
            return False
        name = where[0]
        return name in self._hosts or (is_wildcard(self.host) and is_ip(name))

    def _host_refusal(self, request: web.Request) -> tuple[web.Response | None, tuple[str, int] | None]:
        """A 400 for a Host header that does not name this server (None: it does), and the Host parsed."""
        host = request.headers.get("Host")
        where = split_authority(host) if host is not None else None
        if self._host_ok(where):
            return None, where
        allowed = f"{self.host}:{self.port}" if not is_wildcard(self.host) else f"<this machine>:{self.port}"
        why = f"Host header {shown(host)} does not name this server; allowed: {allowed}"
        return self._refuse(400, "bad Host", why), where

    def _refusal(self, request: web.Request) -> web.Response | None:
        """The answer to a request that may not be served (None: it may)."""
        return self._host_refusal(request)[0]

    def _refuse(self, status: int, kind: str, why: str) -> web.Response:
        self.rejections.add(kind, why)
        return web.Response(status=status, text=why)

    def _unhandled(self, error: BaseException | None) -> None:
        self.errors += 1
        self.rejections.add("internal error", repr(error))
        if self.errors == 1:
            self.log.error("%s: unexpected error", self.what, exc_info=error)

    # --- the application ---

    @web.middleware
    async def _guard(
        self, request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
    ) -> web.StreamResponse:
        refusal = self._refusal(request)
        if refusal is not None:
            return refusal
        try:
            return await handler(request)
        except web.HTTPException:
            raise
        except Exception as e:
            self._unhandled(e)
            return web.Response(status=500, text="internal error")

    @staticmethod
    async def _secure_headers(request: web.Request, response: web.StreamResponse) -> None:
        response.headers.update(SECURITY_HEADERS)

    def _guarded_app(self, **kwargs: Any) -> web.Application:
        """A ``web.Application`` behind the guard, whose every response carries :data:`SECURITY_HEADERS`."""
        app = web.Application(middlewares=[self._guard], **kwargs)
        app.on_response_prepare.append(self._secure_headers)
        return app

    def _protocol(self) -> asyncio.BaseProtocol:
        """aiohttp's handler for a new connection, or, past ``max_http_connections``, a 503 and a close."""
        assert self._runner is not None and self._runner.server is not None
        server = self._runner.server
        if len(server.connections) >= self.max_http_connections:
            self.rejections.add(
                "too many connections",
                f"{len(server.connections)} open; allowed: {self.max_http_connections}",
            )
            return _Refused(self.busy_text)
        return server()

    def _loop_error(self, loop: asyncio.AbstractEventLoop, context: dict[str, Any]) -> None:
        self._unhandled(context.get("exception") or RuntimeError(str(context.get("message"))))

    async def _log_rejections(self) -> None:
        while True:
            await asyncio.sleep(self.rejections.interval)
            self.rejections.flush()

    async def _listen(self, app: web.Application, shutdown_timeout: float) -> None:
        """Serve ``app`` on ``host:port`` (the bound port is in ``port`` afterwards)."""
        loop = asyncio.get_running_loop()
        self._runner = web.AppRunner(
            app,
            access_log=None,
            shutdown_timeout=shutdown_timeout,
            logger=_CountingLogger(self),
            keepalive_timeout=self.idle_timeout_s,
        )
        await self._runner.setup()
        self._listener = await loop.create_server(self._protocol, self.host, self.port, reuse_address=True)
        self.port = int(self._listener.sockets[0].getsockname()[1])
        self._hosts = self._names()

    async def _close_listener(self) -> None:
        """Stop listening, then close the open connections (idempotent)."""
        if self._listener is not None:
            self._listener.close()
        if self._runner is not None:
            runner, self._runner = self._runner, None
            await runner.cleanup()

    # --- running, in a thread of its own ---

    @property
    def url(self) -> str:
        """The address the subclass's users open."""
        raise NotImplementedError

    def _app(self) -> web.Application:
        """The subclass's application, built with :meth:`_guarded_app`."""
        raise NotImplementedError

    async def _setup(self) -> None:
        """What the subclass opens on the server's loop before it listens."""

    def _tasks(self) -> list[Coroutine[Any, Any, None]]:
        """What runs on the loop while it serves (cancelled when it stops)."""
        return [self._log_rejections()]

    async def _teardown(self) -> None:
        """What the subclass closes on the loop after the listener and every task."""

    async def _shutdown(self) -> None:
        """Close the subclass's pages (saying why), then the listener."""
        await self._close_listener()

    def _serve(self) -> None:
        loop = asyncio.new_event_loop()
        self._loop = loop
        asyncio.set_event_loop(loop)
        loop.set_exception_handler(self._loop_error)

        async def start() -> None:
            await self._setup()
            await self._listen(self._app(), self.close_timeout_s)

        try:
            loop.run_until_complete(start())
        except BaseException as e:  # the port is taken, the address is not ours...
            self._error = e
            with contextlib.suppress(Exception):  # what _setup opened (the study's web client) is closed
                loop.run_until_complete(self._teardown())
            loop.close()
            self._started.set()
            return
        tasks = [loop.create_task(work) for work in self._tasks()]
        self._started.set()
        loop.run_forever()
        for task in tasks:
            task.cancel()
        loop.run_until_complete(self._close_listener())
        pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
        for task in pending:
            task.cancel()
        loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
        loop.run_until_complete(self._teardown())
        self.rejections.flush()
        loop.close()

    def start(self) -> str:
        """Serve in a daemon thread; returns :attr:`url`. Raises OSError if the address is unusable."""
        self._thread = threading.Thread(target=self._serve, name=self.thread_name, daemon=True)
        self._thread.start()
        self._started.wait(timeout=30)
        if self._error is not None:
            raise OSError(f"cannot serve {self.serving} on {self.host}:{self.port}: {self._error}")
        return self.url

    def _stop_loop(self, shutdown: Callable[[], Coroutine[Any, Any, None]]) -> None:
        """Run ``shutdown()`` on the server's loop, then stop the loop and join its thread (nothing when it
        is not serving). Call it from another thread than the server's."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or not thread.is_alive():
            return
        with contextlib.suppress(Exception):  # a shutdown slower than the timeout: the loop stops anyway
            asyncio.run_coroutine_threadsafe(shutdown(), loop).result(timeout=self.stop_timeout_s)
        if loop.is_running():
            loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=self.stop_timeout_s)

    def stop(self) -> None:
        """Close the pages, then stop serving; idempotent."""
        self._stop_loop(self._shutdown)

    def __enter__(self: _Server) -> _Server:
        self.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()
