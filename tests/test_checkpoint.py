"""Checkpoints: round trip, and one-line errors for missing, corrupt, foreign or wrong-domain files."""

from __future__ import annotations

import pickle

import pytest
import torch

from hfrl_torch.common.checkpoint import load_checkpoint, save_checkpoint
from hfrl_torch.common.errors import CheckpointError


def _save(path, domain="tetris", agent="cem"):
    return save_checkpoint(
        path, domain=domain, agent=agent, config_yaml="seed: 0\n", payload={"state": {"w": torch.arange(3.0)}}
    )


def test_round_trip_and_run_directory(tmp_path):
    _save(tmp_path / "checkpoints" / "last.pt")
    blob = load_checkpoint(tmp_path, domain="tetris", agent="cem")
    assert torch.equal(blob["state"]["w"], torch.arange(3.0))
    assert blob["config"] == "seed: 0\n"
    assert not list((tmp_path / "checkpoints").glob("*.tmp"))


def test_missing(tmp_path):
    with pytest.raises(CheckpointError, match="does not exist"):
        load_checkpoint(tmp_path / "nope.pt")


def test_truncated_file(tmp_path):
    path = _save(tmp_path / "c.pt")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(path)


def test_garbage_file(tmp_path):
    path = tmp_path / "c.pt"
    path.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="corrupt"):
        load_checkpoint(path)


def test_wrong_domain_and_agent(tmp_path):
    path = _save(tmp_path / "c.pt", domain="keepaway", agent="sarsa")
    with pytest.raises(CheckpointError, match="for domain 'keepaway', not 'tetris'"):
        load_checkpoint(path, domain="tetris")
    with pytest.raises(CheckpointError, match="for agent 'sarsa', not 'cem'"):
        load_checkpoint(path, agent="cem")


def test_foreign_torch_file(tmp_path):
    path = tmp_path / "c.pt"
    torch.save({"weights": torch.zeros(2)}, path)
    with pytest.raises(CheckpointError, match="not an hfrl_torch checkpoint"):
        load_checkpoint(path)


class _Evil:
    def __reduce__(self):
        return (exec, ("import pathlib; pathlib.Path('PWNED').write_text('x')",))


def test_a_checkpoint_cannot_run_code(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.pt"
    with path.open("wb") as f:
        pickle.dump({"format": "hfrl_torch-checkpoint", "x": _Evil()}, f)
    with pytest.raises(CheckpointError):
        load_checkpoint(path)
    assert not (tmp_path / "PWNED").exists()
