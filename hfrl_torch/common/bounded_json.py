"""JSON from untrusted text, parsed within bounds: nesting depth, integer digits, number length, no NaN.

``json.loads`` alone turns a 400-digit integer into an int that overflows the first float conversion,
recurses once per nesting level (``RecursionError`` past about a thousand) and accepts ``NaN`` and
``Infinity``. :func:`loads_bounded` refuses all of these with a :class:`JSONBoundsError` saying what it met
and what is allowed; the caller bounds the text's length before.
"""

from __future__ import annotations

import json
from typing import Any

__all__ = ["JSONBoundsError", "json_depth", "loads_bounded"]


class JSONBoundsError(ValueError):
    """Text that is not JSON within the bounds (the message says what, in one line).

    ``syntax`` is true when the text is not JSON or UTF-8 at all (what a cut-off write leaves), false when
    it is JSON beyond a bound.
    """

    def __init__(self, reason: str, syntax: bool = False) -> None:
        super().__init__(reason)
        self.syntax = syntax


def json_depth(text: bytes) -> int:
    """How deep arrays and objects nest in ``text`` (brackets inside strings do not count)."""
    depth = deepest = 0
    in_string = escaped = False
    for c in text:
        if in_string:
            if escaped:
                escaped = False
            elif c == 0x5C:
                escaped = True
            elif c == 0x22:
                in_string = False
        elif c == 0x22:
            in_string = True
        elif c in (0x5B, 0x7B):
            depth += 1
            deepest = max(deepest, depth)
        elif c in (0x5D, 0x7D):
            depth -= 1
    return deepest


def loads_bounded(
    text: str | bytes, max_depth: int = 16, max_int_digits: int = 18, max_number_chars: int = 40
) -> Any:
    """The JSON value in ``text``, or :class:`JSONBoundsError` if it is not JSON, nests deeper than
    ``max_depth``, has an integer of more than ``max_int_digits`` digits, a number of more than
    ``max_number_chars`` characters, or NaN/Infinity."""
    raw = text.encode("utf-8", "surrogatepass") if isinstance(text, str) else text
    if isinstance(text, bytes):
        try:
            text = text.decode("utf-8")
        except UnicodeDecodeError:
            raise JSONBoundsError("not UTF-8", syntax=True) from None
    if raw.count(b"[") + raw.count(b"{") > max_depth:  # cheap: most texts cannot nest that deep
        depth = json_depth(raw)
        if depth > max_depth:
            raise JSONBoundsError(f"nested {depth} deep; allowed: at most {max_depth}")

    def integer(digits: str) -> int:
        n = len(digits.lstrip("-"))
        if n > max_int_digits:
            raise JSONBoundsError(f"an integer of {n} digits; allowed: at most {max_int_digits}")
        return int(digits)

    def number(chars: str) -> float:
        if len(chars) > max_number_chars:
            raise JSONBoundsError(f"a number of {len(chars)} characters; allowed: at most {max_number_chars}")
        return float(chars)

    def constant(name: str) -> float:
        raise JSONBoundsError(f"{name}; allowed: finite numbers")

    try:
        return json.loads(text, parse_int=integer, parse_float=number, parse_constant=constant)
    except JSONBoundsError:
        raise
    except ValueError:  # json.JSONDecodeError
        raise JSONBoundsError("not JSON", syntax=True) from None
