"""Participant codes and tokens: 12 characters from ``secrets`` in an alphabet without lookalikes."""

from __future__ import annotations

import re
import secrets

ALPHABET = "ABCDEFGHJKLMNPQRSTUVWXYZ23456789"  # base32 less I, O, 0 and 1 (32 symbols: 60 bits in 12)
CODE_LENGTH = 12
CODE = re.compile(f"[{ALPHABET}]{{{CODE_LENGTH}}}")


def new_code(taken: set[str] | frozenset[str] = frozenset()) -> str:
    """A fresh participant code not in ``taken``."""
    while True:
        code = "".join(secrets.choice(ALPHABET) for _ in range(CODE_LENGTH))
        if code not in taken:
            return code


def normalise(code: object) -> str | None:
    """``code`` as stored (upper case, spaces and dashes dropped), or None when it cannot be a code."""
    if not isinstance(code, str) or len(code) > 64:
        return None
    cleaned = code.strip().upper().replace("-", "").replace(" ", "")
    return cleaned if CODE.fullmatch(cleaned) else None


def new_token() -> str:
    """A secret for a URL or a header (researcher, worker): 32 bytes, URL-safe."""
    return secrets.token_urlsafe(32)
