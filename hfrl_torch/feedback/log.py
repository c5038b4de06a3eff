"""The feedback log: every feedback event, one JSON line each, written to disk as it is given, exactly once.

A person's feedback cannot be regenerated, so each line is flushed and fsync'd before ``append`` returns:
a crash loses nothing already logged. The log is what replays and audits read.

**Format** (JSON lines, UTF-8, version 2). Every session starts with a header line
``{"schema": "hfrl_torch.feedback", "version": 2, "session": ..., "created": <wall-clock s>}``, followed by
one line per event ``{"time", "step", "episode", "value", "source", "session", "seq"}``. Reopening a log
appends a new header and the new session's events. Version 1 (no ``seq``) is still read, also mixed with
version 2 in one file (an old log reopened by this build).

**Event ids.** ``(session, seq)`` names an event for good (``FeedbackEvent.id``): ``seq`` is its number in
its session (the event's own ``session`` label, e.g. ``run/board3``), 0, 1, 2..., given only by
:class:`FeedbackLog` when it writes the event (whatever ``seq`` the event came with); a reopened log
continues each session after the largest ``seq`` already in the file.

**Duplicates.** A reader keeps one copy of each event and counts the others
(:attr:`FeedbackLogContents.duplicates`; :func:`load_feedback_log` warns with the count): an event with an
id seen before, or an event equal in every field but ``seq`` to one of an earlier segment (header) of the
file: what a resumed run re-logged before ids existed (version 1), or re-logs with new ids when its
trainer gives again what it gave before the kill and the rewind's matching has ended. A person's press
with an id (source ``human:...``) is never such a copy, since a resumed run cannot give it again: two Good
presses on one placement are equal in every field but ``seq``, and the loop may log one before a kill and
the journal's recovery the other in the next segment; both are kept. Equal events within one segment are
distinct presses (a replay can give two on one placement) and are all kept.

**Exactly once across a kill** (write-ahead). The loop logs events before it learns from them and stores
:attr:`FeedbackLog.last_seq` (per session, the last event it handed to the learner) in each checkpoint. A
resumed run then, per session:

* deterministic sources (simulated trainers, replays), which give the same events again from the restored
  state: :meth:`FeedbackLog.rewind` to the checkpoint's ``last_seq`` before the trainer gives again. Each
  event given again is matched with the logged copy of the same id (same content) and returned without
  being written; past the logged tail new events are written. An event that differs (the source did not
  repeat itself) ends the matching with a warning: the unmatched logged events stay in the file, unlearned,
  and new events get new ids.
* a person: presses cannot be given again, so the loop learns the logged ones it had not learned yet,
  :meth:`FeedbackLog.logged_after` the checkpoint's ``last_seq``, and does not rewind that session.

**Bounds.** A reader parses at most :data:`MAX_LINE_BYTES` per line, nesting :data:`MAX_DEPTH` deep,
integers of :data:`MAX_INT_DIGITS` digits and numbers of :data:`MAX_NUMBER_CHARS` characters, and no
NaN/Infinity: anything else is a corrupt line (``FeedbackLogError`` naming file and line), never an
``OverflowError`` or ``RecursionError``. The writer never writes a line the reader would refuse.
"""

from __future__ import annotations

import json
import os
import threading
import time
import warnings
from collections import Counter
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, overload

from hfrl_torch.common.bounded_json import JSONBoundsError, loads_bounded
from hfrl_torch.common.errors import UserError
from hfrl_torch.feedback.events import EVENT_FIELDS, SOURCE_KINDS, FeedbackEvent, source_kind

__all__ = [
    "MAX_LINE_BYTES",
    "SCHEMA",
    "VERSION",
    "DuplicateFeedbackWarning",
    "FeedbackLog",
    "FeedbackLogContents",
    "FeedbackLogError",
    "load_feedback_log",
    "read_feedback_log",
]

SCHEMA = "hfrl_torch.feedback"
HUMAN = SOURCE_KINDS.index("human")  # the source kind of a person's presses
VERSION = 2
READS = (1, 2)
MAX_LINE_BYTES = 16384  # an event line is about 150 bytes
MAX_DEPTH = 16  # lines are flat objects (depth 1)
MAX_INT_DIGITS = 18  # every integer field fits in int64
MAX_NUMBER_CHARS = 40  # repr of any float64 is at most 24
_V1_FIELDS = EVENT_FIELDS[:-1]


class FeedbackLogError(UserError):
    """A feedback log that is missing, corrupt, or of another schema/version.

    ``events`` holds the valid events read before the problem (one copy of each), so a caller can keep
    them; ``line`` is the 1-based line number of the problem (0 when the file as a whole is the problem);
    ``truncated`` says the problem is an incomplete last line (no newline, not valid JSON), what an
    interrupted write leaves; ``duplicates`` counts the copies dropped before it.
    """

    def __init__(
        self,
        message: str,
        events: list[FeedbackEvent] | None = None,
        line: int = 0,
        truncated: bool = False,
        duplicates: int = 0,
    ) -> None:
        super().__init__(message)
        self.events: list[FeedbackEvent] = list(events or [])
        self.line = line
        self.truncated = truncated
        self.duplicates = duplicates


class DuplicateFeedbackWarning(UserWarning):
    """A feedback log held the same event more than once; one copy of each was kept."""


@dataclass(frozen=True)
class FeedbackLogContents:
    """What a read of a feedback log found.

    :param events: one copy of each event, in the order written (up to ``error``).
    :param duplicates: copies dropped (same id, or re-logged in a later segment; see the module).
    :param last_seq: per session, the largest ``seq`` in the file, duplicates included.
    :param error: the problem that ended the read (None: the whole file was read).
    """

    events: list[FeedbackEvent]
    duplicates: int = 0
    last_seq: dict[str, int] = field(default_factory=dict)
    error: FeedbackLogError | None = None


def _parse(body: bytes) -> Any:
    """One line's JSON value, within the module's bounds, or ``JSONBoundsError``."""
    return loads_bounded(body, MAX_DEPTH, MAX_INT_DIGITS, MAX_NUMBER_CHARS)


def _content(ev: FeedbackEvent) -> tuple[Any, ...]:
    return (ev.time, ev.step, ev.episode, ev.value, ev.source, ev.session)


class _Reader:
    """Reads a log line by line, checking each and dropping duplicates."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.events: list[FeedbackEvent] = []
        self.duplicates = 0
        self.last_seq: dict[str, int] = {}
        self.version = 0
        self._ids: set[tuple[str, int]] = set()
        self._earlier: Counter[tuple[Any, ...]] = Counter()  # most copies of each content in one segment
        self._segment: Counter[tuple[Any, ...]] = Counter()

    def error(self, message: str, line: int = 0, truncated: bool = False) -> FeedbackLogError:
        return FeedbackLogError(message, self.events, line, truncated, self.duplicates)

    def read(self) -> FeedbackLogContents:
        try:
            self._lines()
        except FeedbackLogError as e:
            return FeedbackLogContents(self.events, self.duplicates, self.last_seq, e)
        return FeedbackLogContents(self.events, self.duplicates, self.last_seq)

    def _lines(self) -> None:
        path = self.path
        if not path.exists():
            raise self.error(f"feedback log {path} does not exist")
        if not path.is_file():
            raise self.error(f"feedback log {path} is not a file")
        with path.open("rb") as f:
            lineno = 0
            while raw := f.readline(MAX_LINE_BYTES + 1):
                lineno += 1
                terminated = raw.endswith(b"\n")
                if not terminated and len(raw) > MAX_LINE_BYTES:
                    raise self.error(
                        f"{path}:{lineno}: corrupt line (longer than {MAX_LINE_BYTES} bytes)", lineno
                    )
                try:
                    obj = _parse(raw[:-1] if terminated else raw)
                except JSONBoundsError as e:
                    if e.syntax and not terminated:
                        raise self.error(
                            f"{path}:{lineno}: truncated last line (an interrupted write)", lineno, True
                        ) from None
                    raise self.error(f"{path}:{lineno}: corrupt line ({e})", lineno) from None
                if not isinstance(obj, dict):
                    raise self.error(f"{path}:{lineno}: corrupt line (not a JSON object)", lineno)
                if lineno == 1 or "schema" in obj:
                    self._header(obj, lineno)
                else:
                    self._event(obj, lineno)
        if lineno == 0:
            raise self.error(f"{path}: empty file, not a feedback log (no header line)", 1)

    def _header(self, obj: dict[str, Any], lineno: int) -> None:
        path = self.path
        if obj.get("schema") != SCHEMA:
            raise self.error(
                f"{path}:{lineno}: not a feedback log (schema {obj.get('schema')!r}, expected {SCHEMA!r})",
                lineno,
            )
        version = obj.get("version")
        if type(version) is not int or version not in READS:
            raise self.error(
                f"{path}:{lineno}: feedback log version {version!r}; this build reads "
                f"{' and '.join(map(str, READS))}",
                lineno,
            )
        self.version = version
        for content, n in self._segment.items():
            if n > self._earlier[content]:
                self._earlier[content] = n
        self._segment.clear()

    def _event(self, obj: dict[str, Any], lineno: int) -> None:
        path = self.path
        names = EVENT_FIELDS if self.version >= 2 else _V1_FIELDS
        missing = [k for k in names if k not in obj]
        if missing:
            raise self.error(f"{path}:{lineno}: corrupt feedback event, missing {', '.join(missing)}", lineno)
        try:
            ev = FeedbackEvent(**{k: obj[k] for k in names})
        except (ValueError, TypeError) as e:
            raise self.error(f"{path}:{lineno}: corrupt feedback event: {e}", lineno) from None
        if self.version >= 2 and ev.seq < 0:
            raise self.error(f"{path}:{lineno}: corrupt feedback event: seq={ev.seq}, must be >= 0", lineno)
        content = _content(ev)
        self._segment[content] += 1
        if ev.id is not None:
            self.last_seq[ev.session] = max(self.last_seq.get(ev.session, -1), ev.seq)
            if ev.id in self._ids:
                self.duplicates += 1
                return
            self._ids.add(ev.id)
        pressed = ev.id is not None and source_kind(ev.source) == HUMAN  # never given again
        if not pressed and self._segment[content] <= self._earlier[content]:
            self.duplicates += 1
            return
        self.events.append(ev)


def read_feedback_log(path: str | os.PathLike[str]) -> FeedbackLogContents:
    """Read a feedback log: one copy of each event, the duplicates dropped, and the problem that ended the
    read, if any (never raises ``FeedbackLogError``: it is in ``.error``)."""
    return _Reader(Path(path)).read()


@overload
def load_feedback_log(path: str | os.PathLike[str], strict: Literal[True] = ...) -> list[FeedbackEvent]: ...


@overload
def load_feedback_log(
    path: str | os.PathLike[str], strict: Literal[False]
) -> tuple[list[FeedbackEvent], FeedbackLogError | None]: ...


def load_feedback_log(
    path: str | os.PathLike[str], strict: bool = True
) -> list[FeedbackEvent] | tuple[list[FeedbackEvent], FeedbackLogError | None]:
    """Every event of a feedback log, once each, in the order written (all sessions).

    Duplicates are dropped with a :class:`DuplicateFeedbackWarning` naming how many (the count is
    :func:`read_feedback_log`'s ``duplicates``). With ``strict=True`` a missing file, wrong schema/version
    or a truncated/corrupt line raises ``FeedbackLogError`` naming the file and line, carrying the valid
    events before it in ``.events``. With ``strict=False`` it never raises that error: it returns
    ``(valid prefix, error or None)``.
    """
    contents = read_feedback_log(path)
    if contents.duplicates:
        warnings.warn(
            f"{path}: dropped {contents.duplicates} duplicate feedback events (an id seen before, or an "
            "event logged again by a resumed run); one copy of each is kept",
            DuplicateFeedbackWarning,
            stacklevel=2,
        )
    if strict:
        if contents.error is not None:
            raise contents.error
        return contents.events
    return contents.events, contents.error


def _line(obj: dict[str, Any]) -> bytes:
    line = (json.dumps(obj, allow_nan=False) + "\n").encode("utf-8")
    if len(line) - 1 > MAX_LINE_BYTES:
        raise ValueError(
            f"a feedback log line of {len(line) - 1} bytes is too long; allowed: at most {MAX_LINE_BYTES} "
            "(shorten the session or source)"
        )
    return line


def drop_partial_line(path: Path) -> bool:
    """Cut an incomplete last line (no newline: what a write cut short by a kill leaves) off an append-only
    JSON-lines file, fsync'd; returns whether there was one."""
    data = path.read_bytes()
    if not data or data.endswith(b"\n"):
        return False
    with open(path, "r+b") as f:
        f.truncate(data.rfind(b"\n") + 1)
        f.flush()
        os.fsync(f.fileno())
    return True


class FeedbackLog:
    """Append-only feedback log for one session; every ``append`` is flushed and fsync'd before it returns.

    Opening an existing log checks it first and refuses (``FeedbackLogError``) one that cannot be read
    back, so new events never land after a corrupt line. One exception: an incomplete last line, what a
    crash in the middle of a write leaves, is cut off with a warning (it holds no complete event).
    ``fsync=False`` keeps the flush but skips the fsync, for fast simulated trainers where a power cut
    costing the last events is acceptable. Thread-safe.

    Every event written gets its ``seq`` here (see the module); :attr:`last_seq`, :meth:`rewind` and
    :meth:`logged_after` are what a resumed run needs to give each event to its learner exactly once.
    """

    def __init__(self, path: str | os.PathLike[str], session: str, fsync: bool = True) -> None:
        if not (isinstance(session, str) and session.strip()):
            raise ValueError(f"FeedbackLog session must be a non-empty string, got {session!r}")
        header = _line({"schema": SCHEMA, "version": VERSION, "session": session, "created": time.time()})
        self.path = Path(path)
        self.session = session
        self.fsync = fsync
        self.count = 0  # events written by this object
        self.matched = 0  # events given again after a rewind, found in the file and not written again
        self._lock = threading.Lock()
        self._written: dict[str, int] = {}  # largest seq in the file, per session
        self._last: dict[str, int] = {}  # last seq given out, per session
        self._pending: dict[str, dict[int, FeedbackEvent]] = {}  # rewound: logged events to be given again
        if self.path.exists() and self.path.stat().st_size > 0:
            self._written = self._check_existing()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        self._last = dict(self._written)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        with self._lock:
            self._write_locked(header)

    def _check_existing(self) -> dict[str, int]:
        """Check the file before appending (cutting off an interrupted last line); its largest seqs."""
        contents = read_feedback_log(self.path)
        e = contents.error
        if e is not None:
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
            drop_partial_line(self.path)
            return contents.last_seq
        with open(self.path, "r+b") as f:
            f.seek(-1, os.SEEK_END)
            if f.read(1) != b"\n":
                f.write(b"\n")
                f.flush()
                os.fsync(f.fileno())
        return contents.last_seq

    def _write_locked(self, buf: bytes) -> None:
        if self._fd is None:
            raise ValueError(f"feedback log {self.path} is closed")
        view = memoryview(buf)
        while view:
            n = os.write(self._fd, view)
            view = view[n:]
        if self.fsync:
            os.fsync(self._fd)

    @property
    def last_seq(self) -> dict[str, int]:
        """Per session, the ``seq`` of the last event given out (written, or matched after a rewind): what a
        checkpoint stores as the last event its learner has seen."""
        with self._lock:
            return dict(self._last)

    def append(self, event: FeedbackEvent) -> FeedbackEvent:
        """Write one event (``session`` set to this log's if it was ``""``); returns what was written."""
        return self.extend([event])[0]

    def extend(self, events: Iterable[FeedbackEvent]) -> list[FeedbackEvent]:
        """Write several events with one write and one fsync; returns them as written, each with its
        ``session`` (this log's if it was ``""``) and ``seq``. After :meth:`rewind`, an event given again
        is returned as logged and not written again."""
        given = list(events)
        if not given:  # most boards' steps: nothing to write or match
            return []
        for ev in given:
            if not isinstance(ev, FeedbackEvent):
                raise TypeError(f"FeedbackLog takes FeedbackEvent objects, got {type(ev).__name__}")
        with self._lock:
            last, written = dict(self._last), dict(self._written)
            out: list[FeedbackEvent] = []
            lines: list[bytes] = []
            matched = 0
            for ev in given:
                session = ev.session or self.session
                seq = last.get(session, -1) + 1
                stamped = ev.stamped(session, seq)
                pending = self._pending.get(session)
                if pending is not None:
                    logged = pending.pop(seq, None)
                    if logged is not None and _content(logged) == _content(stamped):
                        last[session] = seq
                        out.append(logged)
                        matched += 1
                        if not pending:
                            del self._pending[session]
                        continue
                    if logged is not None:
                        self._diverged(session, seq, len(pending) + 1, written.get(session, -1))
                        seq = written.get(session, -1) + 1
                        stamped = stamped.stamped(session, seq)
                    if not pending or logged is not None:
                        del self._pending[session]
                lines.append(_line(stamped.to_dict()))
                last[session] = seq
                written[session] = max(written.get(session, -1), seq)
                out.append(stamped)
            if lines:
                self._write_locked(b"".join(lines))
            self._last, self._written = last, written
            self.count += len(lines)
            self.matched += matched
        return out

    def _diverged(self, session: str, seq: int, left: int, end: int) -> None:
        warnings.warn(
            f"{self.path}: event {seq} of session {session!r}, given again after a resume, differs from the "
            f"logged one: the trainer did not repeat itself, so {left} logged events from {seq} on stay "
            f"unlearned in the log and new events continue after {end}",
            stacklevel=4,
        )

    def rewind(self, last_seq: Mapping[str, int]) -> int:
        """A resumed run's learner has seen each session's events up to ``last_seq[session]`` (from its
        checkpoint): the events its trainer gives next are taken as the logged ones that follow, given
        again, and are not written twice. Returns how many logged events await being given again."""
        contents = read_feedback_log(self.path)
        if contents.error is not None:
            raise contents.error
        with self._lock:
            waiting = 0
            for session, seq in last_seq.items():
                if not (isinstance(seq, int) and not isinstance(seq, bool) and seq >= -1):
                    raise ValueError(
                        f"rewind: the last seq of session {session!r} must be an integer >= -1, got {seq!r}"
                    )
                have = self._written.get(session, -1)
                if seq > have:
                    warnings.warn(
                        f"{self.path}: the checkpoint has seen events up to {seq} of session {session!r} but "
                        f"the log ends at {have} (lost with fsync=False?); new events continue after {seq}",
                        stacklevel=2,
                    )
                    self._written[session] = seq
                self._last[session] = seq
                pending = {e.seq: e for e in contents.events if e.session == session and e.seq > seq}
                if pending:
                    self._pending[session] = pending
                else:
                    self._pending.pop(session, None)
                waiting += len(pending)
        return waiting

    def resume(self, last_seq: Mapping[str, int], regenerated: bool) -> list[FeedbackEvent]:
        """Continue a checkpoint's feedback exactly once: every session of the log is taken as seen up to
        ``last_seq`` (-1 for one the checkpoint never saw). With ``regenerated`` (a simulated trainer or a
        replay, restored to the checkpoint's state, gives the same events again) the log :meth:`rewind` s;
        otherwise (a person) it returns the logged events the learner has not seen, to be learned."""
        seen = {session: -1 for session in self.last_seq}
        seen.update({str(k): int(v) for k, v in last_seq.items()})
        if regenerated:
            self.rewind(seen)
            return []
        return self.logged_after(seen)

    def logged_after(self, last_seq: Mapping[str, int]) -> list[FeedbackEvent]:
        """The logged events of the sessions in ``last_seq`` after ``last_seq[session]``, in the order
        written: what a resumed learner has not seen (a person's presses, which cannot be given again)."""
        contents = read_feedback_log(self.path)
        if contents.error is not None:
            raise contents.error
        return [e for e in contents.events if e.session in last_seq and e.seq > last_seq[e.session]]

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
