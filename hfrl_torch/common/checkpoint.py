"""Checkpoints: tensors and plain values, written atomically, checksummed, read with ``weights_only=True``.

A checkpoint can therefore never run code when loaded, an interrupted write never replaces the last good
checkpoint, and a file changed after it was written (a flipped bit, a truncation, an edit) is refused.

**Format (version 2).** The file is an ordinary ``torch.save`` file of one dict: ``format``, ``version``,
``domain``, ``agent``, ``config`` (the run's YAML), the payload's own keys, and ``sha256``. The checksum is
a SHA-256 over a canonical encoding of everything else in the dict (every key, in order; every value with
its type; every tensor's dtype, shape and raw bytes), so ``torch.load(path, weights_only=True)`` still reads
the file directly (``experiment/aggregate.py`` does) and the checksum does not depend on how a torch
version lays out its zip file. Load recomputes it over what was read: any change to what the file holds is
caught, and a change to the zip that leaves the content as it was cannot matter.

**Version 1** files (before the checksum) are still read, with a :class:`CheckpointWarning` naming the file:
they cannot be verified, and refusing them would make every run saved before it unreadable. The next
save of a resumed run writes version 2.

Every problem with a file (missing, truncated, damaged, foreign, wrong types inside, missing keys, made
for another domain or agent) raises :class:`CheckpointError` with one line naming the file and what is
wrong. The dicts :func:`load_checkpoint` returns raise it too (a :class:`MissingCheckpointKey`, also a
``KeyError``) when a caller reads a key the file does not hold.
"""

from __future__ import annotations

import hashlib
import os
import struct
import warnings
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from hfrl_torch.common.errors import CheckpointError

FORMAT = "hfrl_torch-checkpoint"
VERSION = 2
READS = (1, 2)
LAST = "last.pt"
ENVELOPE = ("format", "version", "domain", "agent", "config")
CHECKSUM = "sha256"
MAX_DEPTH = 64  # nesting of dicts and lists; a payload uses about 6
MAX_VALUES = 1 << 24  # values visited while checking one file (a crafted file cannot make a load endless)
ALLOWED = "dicts with str or int keys, lists, tuples, tensors, str, int, float, bool and None"


class CheckpointWarning(UserWarning):
    """A checkpoint was read that cannot be verified (format version 1, before the checksum)."""


class MissingCheckpointKey(CheckpointError, KeyError):
    """A key a caller read is not in the checkpoint (a ``KeyError`` too, for callers that catch that)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


class CheckpointDict(dict):
    """A dict of a loaded checkpoint: a missing key raises :class:`MissingCheckpointKey` naming the file and
    the key's place (``'state' -> 'cem'``), so a caller's plain ``ckpt["state"]`` fails with one line."""

    __slots__ = ("_file", "_where")

    def __init__(self, items: Any = (), *, file: str = "", where: str = "") -> None:
        super().__init__(items)
        self._file, self._where = file, where

    def __missing__(self, key: object) -> Any:
        at = f"{self._where} -> {key!r}" if self._where else repr(key)
        raise MissingCheckpointKey(f"checkpoint {self._file!r} has no {at}")

    def __reduce__(self) -> Any:  # copies and pickles as a plain dict (checkpoints never hold this class)
        return (dict, (dict(self),))


class _Bad(Exception):
    """What is wrong inside a checkpoint's values (becomes a CheckpointError naming the file)."""


def _place(where: str, key: object) -> str:
    return f"{where} -> {key!r}" if where else repr(key)


class _Canonical:
    """Feeds a value's canonical encoding to a hash while rebuilding it with the given dict class."""

    def __init__(self, make_dict: Callable[[dict[Any, Any], str], dict[Any, Any]]) -> None:
        self.hash = hashlib.sha256()
        self.make_dict = make_dict
        self.visited = 0
        self._open: set[int] = set()

    def _size(self, n: int) -> None:
        self.hash.update(struct.pack("<Q", n))

    def value(self, x: Any, where: str = "", depth: int = 0) -> Any:
        self.visited += 1
        if self.visited > MAX_VALUES:
            raise _Bad(f"holds more than {MAX_VALUES} values")
        h = self.hash.update
        if x is None:
            h(b"N")
            return x
        if isinstance(x, bool):
            h(b"B1" if x else b"B0")
            return x
        if type(x) is int:
            raw = x.to_bytes((x.bit_length() + 8) // 8, "little", signed=True)
            h(b"I")
            self._size(len(raw))
            h(raw)
            return x
        if type(x) is float:
            h(b"F" + struct.pack("<d", x))
            return x
        if type(x) is str:
            raw = x.encode("utf-8", "surrogatepass")
            h(b"S")
            self._size(len(raw))
            h(raw)
            return x
        if type(x) is torch.Tensor or type(x) is torch.nn.Parameter:
            return self._tensor(x, where)
        if type(x) in (dict, OrderedDict, CheckpointDict, list, tuple):
            if depth >= MAX_DEPTH:
                raise _Bad(f"is nested deeper than {MAX_DEPTH} levels at {where or 'the top'}")
            if id(x) in self._open:
                raise _Bad(f"refers to itself at {where or 'the top'}")
            self._open.add(id(x))
            try:
                return self._container(x, where, depth)
            finally:
                self._open.discard(id(x))
        raise _Bad(f"holds a {type(x).__name__} at {where or 'the top'}; allowed: {ALLOWED}")

    def _container(self, x: Any, where: str, depth: int) -> Any:
        if isinstance(x, dict):
            self.hash.update(b"D")
            self._size(len(x))
            out: dict[Any, Any] = {}
            for k, v in x.items():
                if not (type(k) is str or type(k) is int):
                    raise _Bad(f"has a {type(k).__name__} key at {where or 'the top'}; allowed: str or int")
                self.value(k, where, depth + 1)
                out[k] = self.value(v, _place(where, k), depth + 1)
            return self.make_dict(out, where)
        self.hash.update(b"L" if type(x) is list else b"T")
        self._size(len(x))
        items = [self.value(v, _place(where, i), depth + 1) for i, v in enumerate(x)]
        return items if type(x) is list else tuple(items)

    def _tensor(self, t: torch.Tensor, where: str) -> torch.Tensor:
        if t.layout != torch.strided or t.is_quantized or t.is_meta:
            raise _Bad(f"holds a {t.layout} tensor at {where or 'the top'}; allowed: dense tensors")
        data = t.detach().resolve_conj().resolve_neg().cpu().contiguous().reshape(-1)
        head = f"X{type(t).__name__}|{data.dtype}|{tuple(t.shape)}|{int(t.requires_grad)}|".encode()
        self.hash.update(head)
        raw = data.view(torch.uint8).numpy()
        self._size(raw.nbytes)
        self.hash.update(memoryview(raw))
        return t


def _plain(items: dict[Any, Any], where: str) -> dict[Any, Any]:
    return items


def checksum(blob: dict[str, Any]) -> str:
    """The SHA-256 (hex) of a checkpoint dict without its ``sha256`` entry; raises ``TypeError`` if it holds
    anything a checkpoint may not."""
    canon = _Canonical(_plain)
    try:
        canon.value({k: v for k, v in blob.items() if k != CHECKSUM})
    except _Bad as e:
        raise TypeError(f"a checkpoint {e}") from None
    return canon.hash.hexdigest()


def save_checkpoint(
    path: str | Path, *, domain: str, agent: str, config_yaml: str, payload: dict[str, Any]
) -> Path:
    """Write ``payload`` (tensors, numbers, strings, lists, dicts) to ``path`` atomically, with its checksum.

    Raises ``TypeError`` (before writing anything) if the payload holds another type or uses a key of the
    checkpoint's own (``format``, ``version``, ``domain``, ``agent``, ``config``, ``sha256``, ``path``).
    """
    path = Path(path)
    taken = sorted(set(payload) & {*ENVELOPE, CHECKSUM, "path"})
    if taken:
        raise TypeError(f"checkpoint payload keys {taken} are the checkpoint's own")
    blob: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "domain": domain,
        "agent": agent,
        "config": config_yaml,
        **payload,
    }
    canon = _Canonical(_plain)
    try:
        plain = canon.value(blob)  # plain dicts: a loaded CheckpointDict saved again stays loadable
    except _Bad as e:
        raise TypeError(f"checkpoint payload {e}") from None
    plain[CHECKSUM] = canon.hash.hexdigest()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(plain, tmp)
    os.replace(tmp, path)
    return path


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    line = text.splitlines()[0] if text else type(exc).__name__
    return line if len(line) <= 200 else line[:197] + "..."


def _short(value: object) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def load_checkpoint(
    path: str | Path, *, domain: str | None = None, agent: str | None = None
) -> dict[str, Any]:
    """Read and verify a checkpoint; a run directory means its ``checkpoints/last.pt``.

    Returns the saved dict (``format``, ``version``, ``domain``, ``agent``, ``config``, the payload's keys)
    plus ``path``. Raises :class:`CheckpointError` with one line if the file is missing, corrupt, changed
    since it was written, not ours, or made for another domain or agent.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoints" / LAST
    where = str(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {where!r} does not exist")
    try:
        with warnings.catch_warnings():  # torch's notes on a foreign pickle add nothing to the error below
            warnings.simplefilter("ignore")
            blob = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # the unpickler of a damaged file raises anything from ValueError to IndexError
        raise CheckpointError(
            f"checkpoint {where!r} is corrupt or not a torch checkpoint ({_first_line(exc)})"
        ) from None
    if type(blob) not in (dict, OrderedDict) or blob.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {where!r} is not an hfrl_torch checkpoint")
    version = blob.get("version")
    if type(version) is not int or version not in READS:
        raise CheckpointError(
            f"checkpoint {where!r} has format version {_short(version)}; this hfrl_torch reads "
            f"{' and '.join(map(str, READS))}"
        )
    stored = blob.get(CHECKSUM)
    if version >= 2 and stored is None:
        raise CheckpointError(f"checkpoint {where!r} (format version {version}) has no checksum")
    if stored is not None and not (
        type(stored) is str and len(stored) == 64 and all(c in "0123456789abcdef" for c in stored)
    ):
        raise CheckpointError(f"checkpoint {where!r} has a malformed checksum {_short(stored)}")
    canon = _Canonical(lambda items, at: CheckpointDict(items, file=where, where=at))
    try:
        loaded = canon.value({k: v for k, v in blob.items() if k != CHECKSUM})
    except _Bad as e:
        raise CheckpointError(f"checkpoint {where!r} {e}") from None
    if stored is not None and canon.hash.hexdigest() != stored:
        raise CheckpointError(
            f"checkpoint {where!r} fails its checksum: it was changed or damaged after it was written"
        )
    for key in ENVELOPE[2:]:
        if key not in loaded:
            raise CheckpointError(f"checkpoint {where!r} has no {key!r}")
        if type(loaded[key]) is not str:
            raise CheckpointError(
                f"checkpoint {where!r} has {key}={_short(loaded[key])} ({type(loaded[key]).__name__}), "
                "not a string"
            )
    if stored is None:
        warnings.warn(
            f"checkpoint {where!r} has format version 1, without a checksum: read unverified",
            CheckpointWarning,
            stacklevel=2,
        )
    if domain is not None and loaded["domain"] != domain:
        raise CheckpointError(
            f"checkpoint {where!r} is for domain {_short(loaded['domain'])}, not {domain!r}"
        )
    if agent is not None and loaded["agent"] != agent:
        raise CheckpointError(f"checkpoint {where!r} is for agent {_short(loaded['agent'])}, not {agent!r}")
    loaded["path"] = where
    return loaded
