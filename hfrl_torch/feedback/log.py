"""The feedback log: every feedback event, one JSON line each, written to disk as it is given.

A person's feedback cannot be regenerated, so each line is flushed and fsync'd before ``append`` returns:
a crash loses nothing already logged. The log is what replays and audits read.

Format (JSON lines, UTF-8): every session starts with a header line
``{"schema": "hfrl_torch.feedback", "version": 1, "session": ..., "created": <wall-clock s>}``, followed by
one line per event ``{"time", "step", "episode", "value", "source", "session"}``. Reopening a log appends a
new header and the new session's events.
"""

from __future__ import annotations

import json
import os
import threading
import time
import warnings
from collections.abc import Iterable
from dataclasses import replace
from pathlib import Path
from typing import Any, Literal, overload

from hfrl_torch.common.errors import UserError
from hfrl_torch.feedback.events import FeedbackEvent

__all__ = ["SCHEMA", "VERSION", "FeedbackLog", "FeedbackLogError", "load_feedback_log"]

SCHEMA = "hfrl_torch.feedback"
VERSION = 1
_EVENT_FIELDS = ("time", "step", "episode", "value", "source", "session")


class FeedbackLogError(UserError):
    """A feedback log that is missing, corrupt, or of another schema/version.

    ``events`` holds the valid events read before the problem, so a caller can keep them; ``line`` is the
    1-based line number of the problem (0 when the file as a whole is the problem); ``truncated`` says the
    problem is an incomplete last line (no newline, not valid JSON), what an interrupted write leaves.
    """

    def __init__(
        self, message: str, events: list[FeedbackEvent] | None = None, line: int = 0, truncated: bool = False
    ) -> None:
        super().__init__(message)
        self.events: list[FeedbackEvent] = list(events or [])
        self.line = line
        self.truncated = truncated


def _header(session: str) -> dict[str, Any]:
    return {"schema": SCHEMA, "version": VERSION, "session": session, "created": time.time()}


def _check_header(obj: dict[str, Any], path: Path, lineno: int, events: list[FeedbackEvent]) -> None:
    if obj.get("schema") != SCHEMA:
        raise FeedbackLogError(
            f"{path}:{lineno}: not a feedback log (schema {obj.get('schema')!r}, expected {SCHEMA!r})",
            events,
            lineno,
        )
    if obj.get("version") != VERSION:
        raise FeedbackLogError(
            f"{path}:{lineno}: feedback log version {obj.get('version')!r}; this build reads {VERSION}",
            events,
            lineno,
        )


def _parse_event(obj: dict[str, Any], path: Path, lineno: int, events: list[FeedbackEvent]) -> FeedbackEvent:
    missing = [k for k in _EVENT_FIELDS if k not in obj]
    if missing:
        raise FeedbackLogError(
            f"{path}:{lineno}: corrupt feedback event, missing {', '.join(missing)}", events, lineno
        )
    try:
        return FeedbackEvent(**{k: obj[k] for k in _EVENT_FIELDS})
    except (ValueError, TypeError) as e:
        raise FeedbackLogError(f"{path}:{lineno}: corrupt feedback event: {e}", events, lineno) from None


def _read(path: Path) -> list[FeedbackEvent]:
    """Events of a log; raises FeedbackLogError carrying the valid prefix."""
    if not path.exists():
        raise FeedbackLogError(f"feedback log {path} does not exist")
    if not path.is_file():
        raise FeedbackLogError(f"feedback log {path} is not a file")
    data = path.read_bytes()
    if not data:
        raise FeedbackLogError(f"{path}: empty file, not a feedback log (no header line)", line=1)
    events: list[FeedbackEvent] = []
    lines = data.split(b"\n")
    if lines[-1] == b"":
        lines.pop()
    for lineno, raw in enumerate(lines, start=1):
        last_unterminated = lineno == len(lines) and not data.endswith(b"\n")
        try:
            obj = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            if last_unterminated:
                raise FeedbackLogError(
                    f"{path}:{lineno}: truncated last line (an interrupted write)", events, lineno, True
                ) from None
            raise FeedbackLogError(f"{path}:{lineno}: corrupt line (not JSON)", events, lineno) from None
        if not isinstance(obj, dict):
            raise FeedbackLogError(f"{path}:{lineno}: corrupt line (not a JSON object)", events, lineno)
        if lineno == 1 or "schema" in obj:
            _check_header(obj, path, lineno, events)
        else:
            events.append(_parse_event(obj, path, lineno, events))
    return events


@overload
def load_feedback_log(path: str | os.PathLike[str], strict: Literal[True] = ...) -> list[FeedbackEvent]: ...


@overload
def load_feedback_log(
    path: str | os.PathLike[str], strict: Literal[False]
) -> tuple[list[FeedbackEvent], FeedbackLogError | None]: ...


def load_feedback_log(
    path: str | os.PathLike[str], strict: bool = True
) -> list[FeedbackEvent] | tuple[list[FeedbackEvent], FeedbackLogError | None]:
    """Every event of a feedback log, in the order written (all sessions).

    With ``strict=True`` a missing file, wrong schema/version or a truncated/corrupt line raises
    ``FeedbackLogError`` naming the file and line, carrying the valid events before it in ``.events``.
    With ``strict=False`` it never raises that error: it returns ``(valid prefix, error or None)``.
    """
    path = Path(path)
    try:
        events = _read(path)
    except FeedbackLogError as e:
        if strict:
            raise
        return e.events, e
    return events if strict else (events, None)


class FeedbackLog:
    """Append-only feedback log for one session; every ``append`` is flushed and fsync'd before it returns.

    Opening an existing log checks it first and refuses (``FeedbackLogError``) one that cannot be read
    back, so new events never land after a corrupt line. One exception: an incomplete last line, what a
    crash in the middle of a write leaves, is cut off with a warning (it holds no complete event).
    ``fsync=False`` keeps the flush but skips the fsync, for fast simulated trainers where a power cut
    costing the last events is acceptable. Thread-safe.
    """

    def __init__(self, path: str | os.PathLike[str], session: str, fsync: bool = True) -> None:
        if not (isinstance(session, str) and session.strip()):
            raise ValueError(f"FeedbackLog session must be a non-empty string, got {session!r}")
        self.path = Path(path)
        self.session = session
        self.fsync = fsync
        self.count = 0
        self._lock = threading.Lock()
        if self.path.exists() and self.path.stat().st_size > 0:
            self._repair_tail()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._write([_header(session)])

    def _repair_tail(self) -> None:
        try:
            _read(self.path)
        except FeedbackLogError as e:
            if not (e.truncated and e.line > 1):
                raise FeedbackLogError(
                    f"will not append to {self.path}: {e} (move it aside or start a new log)",
                    e.events,
                    e.line,
                ) from None
            warnings.warn(
                f"{self.path}:{e.line}: dropping an incomplete last line left by an interrupted write",
                stacklevel=3,
            )
            data = self.path.read_bytes()
            with open(self.path, "r+b") as f:
                f.truncate(data.rfind(b"\n") + 1)
                f.flush()
                os.fsync(f.fileno())
            return
        if not self.path.read_bytes().endswith(b"\n"):
            with open(self.path, "ab") as f:
                f.write(b"\n")
                f.flush()
                os.fsync(f.fileno())

    def _write(self, objs: list[dict[str, Any]]) -> None:
        buf = "".join(json.dumps(o, allow_nan=False) + "\n" for o in objs).encode("utf-8")
        with self._lock:
            if self._fd is None:
                raise ValueError(f"feedback log {self.path} is closed")
            view = memoryview(buf)
            while view:
                n = os.write(self._fd, view)
                view = view[n:]
            if self.fsync:
                os.fsync(self._fd)

    def append(self, event: FeedbackEvent) -> FeedbackEvent:
        """Write one event (``session`` set to this log's if it was ``""``); returns what was written."""
        return self.extend([event])[0]

    def extend(self, events: Iterable[FeedbackEvent]) -> list[FeedbackEvent]:
        """Write several events with one write and one fsync; returns them as written."""
        stamped = []
        for ev in events:
            if not isinstance(ev, FeedbackEvent):
                raise TypeError(f"FeedbackLog takes FeedbackEvent objects, got {type(ev).__name__}")
            stamped.append(ev if ev.session else replace(ev, session=self.session))
        if stamped:
            self._write([ev.to_dict() for ev in stamped])
            self.count += len(stamped)
        return stamped

    def close(self) -> None:
        """Close the file; idempotent."""
        with self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None

    def __enter__(self) -> FeedbackLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        fd = getattr(self, "_fd", None)
        if fd is not None:
            os.close(fd)
