"""What the page may send, checked before anything acts on it: type, fields, value ranges, size.

A message is one JSON object per WebSocket text frame: ``feedback`` (a press, numbered by the page),
``speed``, ``pause``, ``presence`` (here or away) or ``finish`` (end and save the run). Anything else
(binary frames, oversized frames, bad JSON, JSON nested deeper than :data:`MAX_DEPTH`, integers of more
than :data:`MAX_INT_DIGITS` digits, NaN/Infinity, unknown types, wrong types, missing or extra fields,
out-of-range values) raises
``MessageError`` with one line naming the bad value (shortened) and what is allowed; the server counts it,
answers with an error message and goes on. Nothing in here raises anything else, whatever the text.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from hfrl_torch.common.bounded_json import JSONBoundsError, loads_bounded

MIN_SPEED = 0.5  # actions per second
MAX_SPEED = 20.0
MAX_DEPTH = 4  # messages are flat objects
MAX_INT_DIGITS = 6
MAX_NUMBER_CHARS = 32


class MessageError(ValueError):
    """A message from the page that is rejected (the text says why, in one line)."""


MAX_PRESS_ID = 999_999  # the page numbers its presses 0, 1, 2... (wrapping) so acks name the press


@dataclass(frozen=True)
class Feedback:
    """The person pressed good (+1) or bad (-1); ``id`` is the page's number of the press (-1: none), sent
    back in the acknowledgement so that the page counts exactly the presses the run took."""

    value: float
    id: int = -1


@dataclass(frozen=True)
class Speed:
    """The person set the agent's speed (actions per second)."""

    actions_per_s: float


@dataclass(frozen=True)
class Pause:
    """The person paused or resumed the agent."""

    paused: bool


@dataclass(frozen=True)
class Presence:
    """The person says they are here (teaching) or away (the agent learns from the environment)."""

    here: bool


@dataclass(frozen=True)
class Finish:
    """The person asks to end the run now and save it ("Finish and save")."""


Message = Feedback | Speed | Pause | Presence | Finish

_FIELDS: dict[str, tuple[str, ...]] = {
    "feedback": ("value",),
    "speed": ("actions_per_s",),
    "pause": ("paused",),
    "presence": ("here",),
    "finish": (),
}
_OPTIONAL: dict[str, tuple[str, ...]] = {"feedback": ("id",)}


def shown(value: object, limit: int = 40) -> str:
    """``repr(value)``, shortened to about ``limit`` characters (error lines stay short)."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _number(obj: dict[str, Any], key: str) -> float:
    v = obj[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise MessageError(f"{key}={shown(v)} is invalid: must be a finite number")
    return float(v)


def _flag(obj: dict[str, Any], key: str) -> bool:
    v = obj[key]
    if not isinstance(v, bool):
        raise MessageError(f"{key}={shown(v)} is invalid: must be true or false")
    return v


def parse_message(raw: str | bytes, max_bytes: int = 1024) -> Message:
    """The message in ``raw`` (one WebSocket text frame), or ``MessageError``."""
    if not isinstance(raw, (str, bytes)):
        raise MessageError(f"message is a {type(raw).__name__}; allowed: one JSON object as text")
    size = len(raw.encode("utf-8", "surrogatepass") if isinstance(raw, str) else raw)
    if size > max_bytes:
        raise MessageError(f"message of {size} bytes is too large; allowed: at most {max_bytes}")
    try:
        obj = loads_bounded(raw, MAX_DEPTH, MAX_INT_DIGITS, MAX_NUMBER_CHARS)
    except JSONBoundsError as e:
        if e.syntax:
            raise MessageError("message is not valid JSON; allowed: one JSON object") from None
        raise MessageError(f"message holds {e}") from None
    if not isinstance(obj, dict):
        raise MessageError(f"message is a JSON {type(obj).__name__}; allowed: one JSON object")
    kind = obj.get("type")
    if not isinstance(kind, str) or kind not in _FIELDS:
        raise MessageError(f"type={shown(kind)} is invalid; allowed: {', '.join(_FIELDS)}")
    expected = {"type", *_FIELDS[kind]}
    optional = set(_OPTIONAL.get(kind, ()))
    if not expected <= set(obj) <= expected | optional:
        fields = shown(sorted(obj), 80)
        allowed = f"exactly {sorted(expected)}" + (f" and optionally {sorted(optional)}" if optional else "")
        raise MessageError(f"a {kind} message has fields {fields}; allowed: {allowed}")
    if kind == "feedback":
        value = _number(obj, "value")
        if value not in (1.0, -1.0):
            raise MessageError(f"value={shown(obj['value'])} is invalid; allowed: 1 (good) or -1 (bad)")
        press = obj.get("id", -1)
        if isinstance(press, bool) or not isinstance(press, int) or not -1 <= press <= MAX_PRESS_ID:
            raise MessageError(f"id={shown(press)} is invalid; allowed: an integer 0..{MAX_PRESS_ID}")
        return Feedback(value, press)
    if kind == "finish":
        return Finish()
    if kind == "speed":
        speed = _number(obj, "actions_per_s")
        if not MIN_SPEED <= speed <= MAX_SPEED:
            raise MessageError(
                f"actions_per_s={shown(obj['actions_per_s'])} is invalid: "
                f"must be in {MIN_SPEED:g}..{MAX_SPEED:g}"
            )
        return Speed(speed)
    if kind == "pause":
        return Pause(_flag(obj, "paused"))
    return Presence(_flag(obj, "here"))


class RateLimiter:
    """Token bucket: at most ``rate`` messages per second on average, bursts of ``burst``."""

    def __init__(self, rate: float, burst: int) -> None:
        if not rate > 0 or burst < 1:
            raise ValueError(f"RateLimiter needs rate > 0 and burst >= 1, got {rate!r} and {burst!r}")
        self.rate = float(rate)
        self.burst = float(burst)
        self.tokens = float(burst)
        self.last: float | None = None

    def allow(self, now: float) -> bool:
        """Take one token at time ``now`` (seconds); False if none is left."""
        if self.last is not None:
            self.tokens = min(self.burst, self.tokens + (now - self.last) * self.rate)
        self.last = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False
