"""The press journal: each press the page is told was saved is on disk before the page is told.

The training loop writes a press to the feedback log only when it drains the session's queue: a moment
later while the agent plays, never while it is paused. So the session first appends every press it takes to
``presses.jsonl`` beside the feedback log, flushed and fsync'd, and only then acknowledges it. Press ``n`` of
the journal becomes event ``n`` of the feedback log's browser session (:func:`browser_session`,
``<run>/browser``): the loop logs the presses in the order the journal numbered them. A run that starts
again (``resume=``) first logs the journal's presses its log lacks (:meth:`PressJournal.recover`), each
credited at the frame it was filed under, and the resumed learner learns them like any logged press it had
not seen. So a press acknowledged before a kill -9 is logged exactly once.

**Format** (JSON lines, UTF-8): a header ``{"schema": "hfrl_torch.presses", "version": 1, "created": s}``
each time the journal is opened, then one line per press ``{"n", "wall", "value", "source", "episode",
"step", "sim"}``: its number, its wall-clock time, its value, its source, the episode and step of the frame
it was filed under (-1: none) and that frame's game-clock time (null: none).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

from hfrl_torch.common.bounded_json import JSONBoundsError, loads_bounded
from hfrl_torch.common.errors import UserError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, drop_partial_line
from hfrl_torch.interactive.timeline import Shown, credit_time

__all__ = ["JOURNAL_NAME", "JournalEntry", "PressJournal", "PressJournalError", "browser_session"]

SCHEMA = "hfrl_torch.presses"
VERSION = 1
JOURNAL_NAME = "presses.jsonl"
MAX_LINE_BYTES = 4096  # a press line is about 120 bytes
LOG = logging.getLogger(__name__)
_FIELDS = ("n", "wall", "value", "source", "episode", "step", "sim")


class PressJournalError(UserError):
    """A press journal that cannot be read back (the message names the file and line)."""


def browser_session(log_session: str) -> str:
    """The feedback log session of a person's browser presses (numbered as in the journal)."""
    return f"{log_session}/browser"


@dataclass(frozen=True)
class JournalEntry:
    """One press as the journal holds it (see the module for the fields)."""

    n: int
    wall: float
    value: float
    source: str
    episode: int
    step: int
    sim: float | None

    def event(self, session: str, reaction_s: float, discrete: bool) -> FeedbackEvent:
        """The press as the loop would have logged it: credited at the frame it was filed under (without the
        next frame's bound, which only the loop knew), or at its wall time when none was shown."""
        seen = None if self.sim is None else Shown(self.wall, self.sim, self.episode, self.step)
        t = credit_time(seen, None, reaction_s, math.inf, discrete) if seen is not None else self.wall
        return FeedbackEvent(
            time=t,
            value=self.value,
            source=self.source,
            step=self.step,
            episode=self.episode,
            session=session,
        )


def _line(obj: dict[str, object]) -> bytes:
    return json.dumps(obj, allow_nan=False, separators=(",", ":")).encode() + b"\n"


def _entry(obj: object) -> JournalEntry:
    if not isinstance(obj, dict) or set(obj) != set(_FIELDS):
        raise ValueError(f"a press line has the fields {', '.join(_FIELDS)}")
    n, episode, step = obj["n"], obj["episode"], obj["step"]
    if not all(type(v) is int for v in (n, episode, step)) or n < 0:
        raise ValueError("n, episode and step must be integers (n >= 0)")
    wall, value, sim = obj["wall"], obj["value"], obj["sim"]
    if not all(type(v) in (int, float) for v in (wall, value)) or not (
        sim is None or type(sim) in (int, float)
    ):
        raise ValueError("wall, value and sim must be numbers (sim may be null)")
    if not isinstance(obj["source"], str):
        raise ValueError("source must be a string")
    return JournalEntry(
        n, float(wall), float(value), obj["source"], episode, step, None if sim is None else float(sim)
    )


def read_journal(path: Path) -> list[JournalEntry]:
    """The presses of a journal, in order; an incomplete last line (an interrupted write) is left out, any
    other bad line raises :class:`PressJournalError`."""
    entries: list[JournalEntry] = []
    data = path.read_bytes()
    lines = data.split(b"\n")
    for i, raw in enumerate(lines, 1):
        if not raw:
            continue
        last = i == len(lines)  # no newline after it: a write cut short
        try:
            if len(raw) > MAX_LINE_BYTES:
                raise ValueError(f"a line of {len(raw)} bytes; allowed: at most {MAX_LINE_BYTES}")
            obj = loads_bounded(raw, 2, 18, 40)
            if isinstance(obj, dict) and obj.get("schema") == SCHEMA:
                if obj.get("version") != VERSION:
                    raise ValueError(f"version {obj.get('version')!r}; this hfrl_torch reads {VERSION}")
                continue
            entries.append(_entry(obj))
        except (JSONBoundsError, ValueError) as e:
            if last and (not isinstance(e, JSONBoundsError) or e.syntax):
                break
            raise PressJournalError(f"press journal {path}:{i} is corrupt ({e}); move it aside") from None
    return entries


class PressJournal:
    """Appends each press taken, fsync'd, numbered after the journal's and the feedback log's last press.

    :param path: the journal's file (``presses.jsonl`` beside the feedback log).
    :param log: the run's feedback log: presses the journal holds and the log lacks are logged now.
    :param reaction_s: the session's reaction allowance (what the recovered presses are credited with).
    :param discrete: whether a step is a whole move (Tetris placements), for crediting recovered presses.
    """

    def __init__(
        self, path: str | os.PathLike[str], log: FeedbackLog, reaction_s: float, discrete: bool
    ) -> None:
        self.path = Path(path)
        self.session = browser_session(log.session)
        self._lock = threading.Lock()
        entries = read_journal(self.path) if self.path.exists() else []
        self.recovered = self._recover(entries, log, reaction_s, discrete)
        last = max([e.n for e in entries], default=-1)
        self._next = max(last, log.last_seq.get(self.session, -1)) + 1
        if self.path.exists():
            drop_partial_line(self.path)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        self._write(_line({"schema": SCHEMA, "version": VERSION, "created": time.time()}))

    def _recover(
        self, entries: list[JournalEntry], log: FeedbackLog, reaction_s: float, discrete: bool
    ) -> list[FeedbackEvent]:
        """Log the journal's presses that the feedback log lacks (killed before the loop logged them)."""
        logged = log.last_seq.get(self.session, -1)
        missing = [e for e in entries if e.n > logged]
        if not missing:
            return []
        written = log.extend([e.event(self.session, reaction_s, discrete) for e in missing])
        LOG.info(
            "%s: logged %d acknowledged presses the stopped run had not logged yet (presses %d..%d)",
            log.path,
            len(written),
            missing[0].n,
            missing[-1].n,
        )
        if [ev.seq for ev in written] != [e.n for e in missing]:
            warnings.warn(
                f"{self.path}: the journal's presses {missing[0].n}..{missing[-1].n} were logged as "
                f"{written[0].seq}..{written[-1].seq} of {self.session!r} (journal or log changed)",
                stacklevel=3,
            )
        return written

    def _write(self, line: bytes) -> None:
        if self._fd is None:
            raise OSError(f"press journal {self.path} is closed")
        view = memoryview(line)
        while view:
            view = view[os.write(self._fd, view) :]
        os.fsync(self._fd)

    def write(self, wall: float, value: float, source: str, seen: Shown | None) -> int:
        """Append one press (filed under ``seen``; None: no frame) ; returns its number once it is on disk."""
        with self._lock:
            n = self._next
            self._write(
                _line(
                    {
                        "n": n,
                        "wall": float(wall),
                        "value": float(value),
                        "source": source,
                        "episode": -1 if seen is None else seen.episode,
                        "step": -1 if seen is None else seen.step,
                        "sim": None if seen is None else float(seen.sim),
                    }
                )
            )
            self._next = n + 1
            return n

    def close(self) -> None:
        """Close the file; idempotent."""
        with self._lock:
            if self._fd is not None:
                os.close(self._fd)
                self._fd = None
