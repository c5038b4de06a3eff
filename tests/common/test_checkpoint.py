"""Checkpoints: round trip, checksum, one-line errors for missing, corrupt, foreign or wrong-domain files."""

from __future__ import annotations

import copy
import pickle
import random
import warnings

import pytest
import torch

from hfrl_torch.common.checkpoint import (
    CheckpointWarning,
    MissingCheckpointKey,
    checksum,
    load_checkpoint,
    save_checkpoint,
)
from hfrl_torch.common.errors import CheckpointError

WEIGHTS = torch.tensor([0.75, -1.5, 2.25, 3.0], dtype=torch.float64)


def _payload() -> dict:
    g = torch.Generator().manual_seed(0)
    return {
        "state": {
            "w": WEIGHTS.clone(),
            "generator": torch.Generator().manual_seed(1).get_state(),
            "lines": torch.randint(0, 100, (3, 5), generator=g),
            "done": torch.tensor([True, False, True]),
            "iteration": 7,
        },
        "history": [{"iteration": i, "lines": i * 0.5, "note": None} for i in range(4)],
        "policy": {"features": "bt", "weights": [0.1, -0.2], "fused": False},
    }


def _save(path, domain="tetris", agent="cem", payload=None):
    return save_checkpoint(
        path, domain=domain, agent=agent, config_yaml="seed: 0\n", payload=payload or _payload()
    )


def _write_raw(path, blob: dict, with_checksum: bool = True):
    """A file as another writer would make it: ``blob`` as is, with a valid checksum over it."""
    if with_checksum:
        blob = {**blob, "sha256": checksum(blob)}
    torch.save(blob, path)
    return path


def _envelope(**changes) -> dict:
    blob = {"format": "hfrl_torch-checkpoint", "version": 2, "domain": "tetris", "agent": "cem"}
    blob.update({"config": "seed: 0\n", "state": {"w": torch.zeros(2)}})
    blob.update(changes)
    return blob


def _same(a, b) -> bool:
    """Equal in type, structure and every bit of every tensor."""
    if isinstance(a, torch.Tensor):
        return (
            isinstance(b, torch.Tensor)
            and (a.dtype, a.shape) == (b.dtype, b.shape)
            and a.reshape(-1).view(torch.uint8).tolist() == b.reshape(-1).view(torch.uint8).tolist()
        )
    if isinstance(a, dict):
        return isinstance(b, dict) and list(a) == list(b) and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return type(a) is type(b) and a == b


def test_round_trip_and_run_directory(tmp_path):
    _save(tmp_path / "checkpoints" / "last.pt")
    blob = load_checkpoint(tmp_path, domain="tetris", agent="cem")
    assert _same(blob["state"], _payload()["state"]) and _same(blob["history"], _payload()["history"])
    assert blob["config"] == "seed: 0\n" and blob["version"] == 2
    assert blob["path"] == str(tmp_path / "checkpoints" / "last.pt") and "sha256" not in blob
    assert not list((tmp_path / "checkpoints").glob("*.tmp"))
    raw = torch.load(tmp_path / "checkpoints" / "last.pt", weights_only=True)  # still a plain torch file
    assert torch.equal(raw["state"]["w"], WEIGHTS) and len(raw["sha256"]) == 64


def test_a_flipped_sign_bit_in_a_tensor_is_caught(tmp_path):
    path = _save(tmp_path / "c.pt")
    data = bytearray(path.read_bytes())
    at = data.find(WEIGHTS.numpy().tobytes())
    assert at >= 0 and data.count(WEIGHTS.numpy().tobytes()) == 1
    data[at + 8 * 2 + 7] ^= 0x80  # the sign bit of 2.25 (little-endian float64): it becomes -2.25
    path.write_bytes(bytes(data))
    assert torch.load(path, weights_only=True)["state"]["w"][2] == -2.25  # torch alone reads it silently
    with pytest.raises(CheckpointError, match=r"c\.pt' fails its checksum: it was changed or damaged"):
        load_checkpoint(path)


def test_random_mutations_never_load_changed_content_nor_raise_anything_else(tmp_path):
    original = _save(tmp_path / "o.pt").read_bytes()
    reference = load_checkpoint(tmp_path / "o.pt")
    rng = random.Random(20)
    path = tmp_path / "m.pt"
    refused = same = 0
    for _ in range(600):
        data = bytearray(original)
        kind = rng.randrange(4)
        if kind == 0:  # one flipped bit
            data[rng.randrange(len(data))] ^= 1 << rng.randrange(8)
        elif kind == 1:  # a few random bytes
            for _ in range(rng.randint(1, 8)):
                data[rng.randrange(len(data))] = rng.randrange(256)
        elif kind == 2:  # truncated
            data = data[: rng.randrange(len(data))]
        else:  # bytes inserted
            at = rng.randrange(len(data))
            data[at:at] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 4)))
        path.write_bytes(bytes(data))
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", CheckpointWarning)
                loaded = load_checkpoint(path)
        except CheckpointError as e:
            assert "\n" not in str(e) and str(path) in str(e)
            refused += 1
            continue
        # only a change to the zip's bookkeeping that leaves every value as it was may load
        assert _same({**loaded, "path": None}, {**reference, "path": None}), f"mutation {data!r} loaded"
        same += 1
    assert refused + same == 600 and refused >= 500


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


@pytest.mark.parametrize(
    ("changes", "match"),
    [
        ({"domain": 3}, r"has domain=3 \(int\), not a string"),
        ({"config": ["seed: 0"]}, r"has config=\['seed: 0'\] \(list\), not a string"),
        ({"agent": None}, r"has agent=None \(NoneType\), not a string"),
    ],
)
def test_wrong_types_inside_a_well_formed_file(tmp_path, changes, match):
    path = _write_raw(tmp_path / "c.pt", _envelope(**changes))
    with pytest.raises(CheckpointError, match=match):
        load_checkpoint(path)


def test_types_a_checkpoint_may_not_hold(tmp_path):
    path = tmp_path / "c.pt"
    torch.save({**_envelope(state={"dims": torch.Size([2, 3])}), "sha256": "0" * 64}, path)
    with pytest.raises(CheckpointError, match=r"holds a Size at 'state' -> 'dims'; allowed: dicts with"):
        load_checkpoint(path)
    torch.save({**_envelope(state={1.5: 2}), "sha256": "0" * 64}, path)
    with pytest.raises(CheckpointError, match="has a float key at 'state'; allowed: str or int"):
        load_checkpoint(path)
    loop: list = [1]
    loop.append(loop)
    torch.save({**_envelope(history=loop), "sha256": "0" * 64}, path)
    with pytest.raises(CheckpointError, match=r"refers to itself at 'history' -> 1"):
        load_checkpoint(path)
    deep: list = []
    for _ in range(100):
        deep = [deep]
    torch.save({**_envelope(history=deep), "sha256": "0" * 64}, path)
    with pytest.raises(CheckpointError, match="nested deeper than 64 levels"):
        load_checkpoint(path)


def test_missing_keys_give_one_line(tmp_path):
    blob = _envelope()
    del blob["config"]
    with pytest.raises(CheckpointError, match=r"c\.pt' has no 'config'"):
        load_checkpoint(_write_raw(tmp_path / "c.pt", blob))
    loaded = load_checkpoint(_save(tmp_path / "d.pt"))
    with pytest.raises(CheckpointError, match=r"d\.pt' has no 'state' -> 'cem'") as info:
        loaded["state"]["cem"]
    assert isinstance(info.value, KeyError) and isinstance(info.value, MissingCheckpointKey)
    assert str(info.value).startswith("checkpoint ")  # not KeyError's quoted repr
    with pytest.raises(CheckpointError, match=r"has no 'resumes'"):
        loaded["resumes"]
    assert loaded.get("resumes") is None and "resumes" not in loaded


def test_checksum_fields_and_versions(tmp_path):
    path = tmp_path / "c.pt"
    torch.save(_envelope(), path)
    with pytest.raises(CheckpointError, match=r"\(format version 2\) has no checksum"):
        load_checkpoint(path)
    torch.save({**_envelope(), "sha256": "ABC"}, path)
    with pytest.raises(CheckpointError, match="has a malformed checksum 'ABC'"):
        load_checkpoint(path)
    _write_raw(path, _envelope(version=3))
    with pytest.raises(CheckpointError, match="has format version 3; this hfrl_torch reads 1 and 2"):
        load_checkpoint(path)
    _write_raw(path, _envelope(version="2"))
    with pytest.raises(CheckpointError, match="has format version '2'"):
        load_checkpoint(path)


def test_version_1_files_load_with_a_warning(tmp_path):
    path = tmp_path / "old.pt"
    torch.save(_envelope(version=1), path)  # what hfrl_torch wrote before the checksum
    with pytest.warns(CheckpointWarning, match=r"old\.pt' has format version 1, without a checksum"):
        blob = load_checkpoint(path, domain="tetris")
    assert torch.equal(blob["state"]["w"], torch.zeros(2))


def test_save_refuses_what_it_could_not_load_and_writes_nothing(tmp_path):
    with pytest.raises(TypeError, match=r"holds a set at 'state' -> 'seen'"):
        _save(tmp_path / "c.pt", payload={"state": {"seen": {1, 2}}})
    with pytest.raises(TypeError, match=r"keys \['sha256', 'version'\] are the checkpoint's own"):
        _save(tmp_path / "c.pt", payload={"version": 9, "sha256": "x"})
    assert not list(tmp_path.iterdir())


def test_a_loaded_checkpoint_saves_and_copies_as_plain_dicts(tmp_path):
    first = load_checkpoint(_save(tmp_path / "a.pt"))
    again = load_checkpoint(_save(tmp_path / "b.pt", payload={"state": first["state"], "old": first}))
    assert _same(again["state"], first["state"]) and _same(again["old"]["history"], first["history"])
    assert type(copy.deepcopy(first)["state"]) is dict and type(pickle.loads(pickle.dumps(first))) is dict


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
