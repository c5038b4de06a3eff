"""Checkpoints: tensors and plain values only, written atomically, read with ``weights_only=True``.

A checkpoint can therefore never run code when loaded, and an interrupted write
never replaces the last good checkpoint.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any

import torch

from hfrl_torch.common.errors import CheckpointError

FORMAT = "hfrl_torch-checkpoint"
VERSION = 1
LAST = "last.pt"


def save_checkpoint(
    path: str | Path, *, domain: str, agent: str, config_yaml: str, payload: dict[str, Any]
) -> Path:
    """Write ``payload`` (tensors, numbers, strings, lists, dicts) to ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    blob = {"format": FORMAT, "version": VERSION, "domain": domain, "agent": agent, "config": config_yaml}
    blob.update(payload)
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(blob, tmp)
    os.replace(tmp, path)
    return path


def load_checkpoint(
    path: str | Path, *, domain: str | None = None, agent: str | None = None
) -> dict[str, Any]:
    """Read a checkpoint; a run directory means its ``checkpoints/last.pt``.

    Raises :class:`CheckpointError` with one line if the file is missing, corrupt,
    not ours, or made for another domain or agent.
    """
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoints" / LAST
    if not path.is_file():
        raise CheckpointError(f"checkpoint {str(path)!r} does not exist")
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except (pickle.UnpicklingError, RuntimeError, EOFError, ValueError, OSError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(
            f"checkpoint {str(path)!r} is corrupt or not a torch checkpoint ({first})"
        ) from exc
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {str(path)!r} is not an hfrl_torch checkpoint")
    if blob.get("version") != VERSION:
        raise CheckpointError(
            f"checkpoint {str(path)!r} has format version {blob.get('version')!r}; "
            f"this hfrl_torch reads {VERSION}"
        )
    if domain is not None and blob.get("domain") != domain:
        raise CheckpointError(
            f"checkpoint {str(path)!r} is for domain {blob.get('domain')!r}, not {domain!r}"
        )
    if agent is not None and blob.get("agent") != agent:
        raise CheckpointError(f"checkpoint {str(path)!r} is for agent {blob.get('agent')!r}, not {agent!r}")
    blob["path"] = str(path)
    return blob
