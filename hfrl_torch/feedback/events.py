"""Feedback events and the thread-safe queue that carries them from a trainer to the training loop.

A producer (the browser trainer, a simulated trainer, a log replay) pushes timestamped events from its own
thread; the training loop drains whatever has arrived once per step, without blocking.
"""

from __future__ import annotations

import math
import numbers
import threading
from collections import deque
from dataclasses import dataclass
from typing import Any, Literal

import torch

from hfrl_torch import keys

__all__ = [
    "EVENT_FIELDS",
    "MAX_ABS_FEEDBACK",
    "SOURCE_KINDS",
    "FeedbackEvent",
    "FeedbackQueue",
    "FeedbackQueueClosedError",
    "FeedbackQueueFullError",
    "feedback_tensors",
    "source_kind",
]

MAX_ABS_FEEDBACK = 1e3
EVENT_FIELDS = ("time", "step", "episode", "value", "source", "session", "seq")


def _is_real(x: object) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _is_int(x: object) -> bool:
    return isinstance(x, numbers.Integral) and not isinstance(x, bool)


@dataclass(frozen=True)
class FeedbackEvent:
    """One piece of feedback from a trainer (TAMER's scalar h: usually +1 good, -1 bad; silence is no event).

    :param time: wall-clock seconds when it was given (``time.time()``); credit assignment works on it.
    :param value: the feedback, finite, within [-1e3, 1e3].
    :param source: who gave it, e.g. ``"human:browser"``, ``"simulated:oracle"``, ``"replay"``.
    :param session: the training session; ``""`` = not yet assigned (``FeedbackLog.append`` fills it in).
    :param step: the agent step it was given at; -1 = not yet known.
    :param episode: the episode it was given in; -1 = not yet known.
    :param seq: its number within its session, 0, 1, 2...; -1 = not yet logged. Only ``FeedbackLog``
        assigns it, when it writes the event; ``(session, seq)`` is then the event's stable :attr:`id`.
    """

    time: float
    value: float
    source: str
    session: str = ""
    step: int = -1
    episode: int = -1
    seq: int = -1

    def __post_init__(self) -> None:
        if not (_is_real(self.time) and math.isfinite(self.time)):
            raise ValueError(f"FeedbackEvent.time must be finite wall-clock seconds, got {self.time!r}")
        if not (_is_real(self.value) and math.isfinite(self.value) and abs(self.value) <= MAX_ABS_FEEDBACK):
            raise ValueError(
                f"FeedbackEvent.value must be a finite number within [-{MAX_ABS_FEEDBACK:g}, "
                f"{MAX_ABS_FEEDBACK:g}], got {self.value!r}"
            )
        if not (isinstance(self.source, str) and self.source.strip()):
            raise ValueError(f"FeedbackEvent.source must be a non-empty string, got {self.source!r}")
        if not isinstance(self.session, str):
            raise ValueError(f"FeedbackEvent.session must be a string, got {self.session!r}")
        for name in ("step", "episode", "seq"):
            v = getattr(self, name)
            if not (_is_int(v) and v >= -1):
                raise ValueError(f"FeedbackEvent.{name} must be an integer >= 0 (or -1 = unknown), got {v!r}")
        object.__setattr__(self, "time", float(self.time))
        object.__setattr__(self, "value", float(self.value))
        object.__setattr__(self, "step", int(self.step))
        object.__setattr__(self, "episode", int(self.episode))
        object.__setattr__(self, "seq", int(self.seq))

    @property
    def id(self) -> tuple[str, int] | None:
        """``(session, seq)``, the same in every copy of the event; None until a ``FeedbackLog`` wrote it."""
        return (self.session, self.seq) if self.seq >= 0 else None

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able fields, in the order the feedback log writes them."""
        return {k: getattr(self, k) for k in EVENT_FIELDS}  # all plain values: nothing to copy

    def stamped(self, session: str, seq: int | None = None) -> FeedbackEvent:
        """This event under ``session`` (and numbered ``seq``, if given): ``dataclasses.replace`` without
        checking again the fields it keeps (a trainer and the log stamp every event they pass on)."""
        if not isinstance(session, str):
            raise ValueError(f"FeedbackEvent.session must be a string, got {session!r}")
        if seq is not None and not (_is_int(seq) and seq >= -1):
            raise ValueError(f"FeedbackEvent.seq must be an integer >= 0 (or -1 = unknown), got {seq!r}")
        out = object.__new__(type(self))
        fields = out.__dict__
        fields.update(self.__dict__)
        fields["session"] = session
        if seq is not None:
            fields["seq"] = int(seq)
        return out


class FeedbackQueueFullError(RuntimeError):
    """A bounded ``FeedbackQueue`` with ``overflow="error"`` was full."""


class FeedbackQueueClosedError(RuntimeError):
    """``put`` on a ``FeedbackQueue`` after ``close``."""


class FeedbackQueue:
    """Thread-safe FIFO of ``FeedbackEvent`` between producer threads and the training loop.

    Bounded to ``maxsize`` events. When full, ``overflow="drop_oldest"`` (the default) discards the oldest
    waiting event and counts it in ``dropped``: a stalled loop must not block or crash the trainer's UI
    thread, and the newest feedback is the one credit assignment can still use (old events fall out of the
    delay window anyway). ``overflow="error"`` raises ``FeedbackQueueFullError`` instead.
    After ``close()``, ``put`` raises ``FeedbackQueueClosedError`` and ``drain`` still returns what is left.
    """

    def __init__(
        self, maxsize: int = 10_000, overflow: Literal["drop_oldest", "error"] = "drop_oldest"
    ) -> None:
        if not (_is_int(maxsize) and maxsize >= 1):
            raise ValueError(f"FeedbackQueue maxsize must be an integer >= 1, got {maxsize!r}")
        if overflow not in ("drop_oldest", "error"):
            raise ValueError(f"FeedbackQueue overflow must be 'drop_oldest' or 'error', got {overflow!r}")
        self.maxsize = int(maxsize)
        self.overflow = overflow
        self._events: deque[FeedbackEvent] = deque()
        self._cond = threading.Condition(threading.Lock())
        self._closed = False
        self._dropped = 0

    def put(self, event: FeedbackEvent) -> None:
        """Add one event (from any thread); never blocks."""
        if not isinstance(event, FeedbackEvent):
            raise TypeError(f"FeedbackQueue.put takes a FeedbackEvent, got {type(event).__name__}")
        with self._cond:
            if self._closed:
                raise FeedbackQueueClosedError("the feedback queue is closed; no more events are accepted")
            if len(self._events) >= self.maxsize:
                if self.overflow == "error":
                    raise FeedbackQueueFullError(
                        f"the feedback queue is full ({self.maxsize} events not yet drained)"
                    )
                self._events.popleft()
                self._dropped += 1
            self._events.append(event)
            self._cond.notify_all()

    def check_room(self) -> None:
        """Raise what :meth:`put` would raise for one more event now (closed; full with ``overflow="error"``),
        so that a caller can refuse an event before it records it elsewhere."""
        with self._cond:
            if self._closed:
                raise FeedbackQueueClosedError("the feedback queue is closed; no more events are accepted")
            if self.overflow == "error" and len(self._events) >= self.maxsize:
                raise FeedbackQueueFullError(
                    f"the feedback queue is full ({self.maxsize} events not yet drained)"
                )

    def drain(self, timeout: float | None = None) -> list[FeedbackEvent]:
        """Take every waiting event, oldest first. Returns at once unless ``timeout`` (seconds) is given, in
        which case it waits up to that long for at least one event (or ``close``)."""
        with self._cond:
            if timeout is not None and not self._events and not self._closed:
                self._cond.wait_for(lambda: bool(self._events) or self._closed, timeout=timeout)
            events = list(self._events)
            self._events.clear()
            return events

    def close(self) -> None:
        """Refuse further events and wake any waiting ``drain``; idempotent."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        """Whether ``close`` has been called."""
        return self._closed

    @property
    def dropped(self) -> int:
        """How many events ``drop_oldest`` discarded so far."""
        return self._dropped

    def __len__(self) -> int:
        with self._cond:
            return len(self._events)


SOURCE_KINDS: tuple[str, ...] = ("none", "human", "simulated", "replay", "queue", "other")


def source_kind(source: str) -> int:
    """The code of ``source`` in ``SOURCE_KINDS`` (by its prefix before ``:``): 0 = no feedback."""
    kind = source.split(":", 1)[0]
    return SOURCE_KINDS.index(kind) if kind in SOURCE_KINDS[1:] else SOURCE_KINDS.index("other")


def feedback_tensors(events: list[list[FeedbackEvent]]) -> dict[str, torch.Tensor]:
    """One step's events of B boards as the tensordict's feedback entries, each ``[B, 1]``.

    ``human_feedback``: the sum of the values given (0: none); ``human_feedback_time``: the time of the
    latest event (NaN: none); ``human_feedback_source``: the ``SOURCE_KINDS`` code of its source (0: none).
    """
    b = len(events)
    value = torch.tensor([sum(e.value for e in evs) for evs in events], dtype=torch.float64).view(b, 1)
    when = torch.tensor(
        [max((e.time for e in evs), default=math.nan) for evs in events], dtype=torch.float64
    ).view(b, 1)
    kind = torch.tensor(
        [source_kind(max(evs, key=lambda e: e.time).source) if evs else 0 for evs in events],
        dtype=torch.int64,
    ).view(b, 1)
    return {keys.FEEDBACK: value, keys.FEEDBACK_TIME: when, keys.FEEDBACK_SOURCE: kind}
