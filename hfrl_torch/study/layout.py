"""The study directory on disk: every file name, atomic JSON writes and the fsync'd event log.

``experiment.evaluate`` reads a study through this module, so it imports nothing heavier than the
standard library. The layout::

    <dir>/study.json                 the resolved study config (resuming compares it)
    <dir>/researcher_token           0600
    <dir>/codes.txt                  0600, enrollment=codes only
    <dir>/events.jsonl               append-only, fsync'd
    <dir>/participants/<code>/participant.json   written atomically (tmp + os.replace)
    <dir>/participants/<code>/run/   the participant's train.py run directory
    <dir>/participants/<code>/worker.log, worker.pid
    <dir>/results/                   evaluate.py runs=<dir>: the report (summary.md, CSVs, plots)
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

STUDY_JSON = "study.json"
RESEARCHER_TOKEN = "researcher_token"
CODES_TXT = "codes.txt"
EVENTS = "events.jsonl"
PARTICIPANTS = "participants"
PARTICIPANT_JSON = "participant.json"
RUN = "run"
WORKER_LOG = "worker.log"
WORKER_PID = "worker.pid"
RESULTS = "results"  # evaluate.py's default output for a study
# names inside a train.py run directory (the same as experiment's and interactive's; test_layout checks)
CHECKPOINT = "checkpoints/last.pt"
TEACHING_SUMMARY = "teaching_summary.json"
PRESSES = "presses.jsonl"
FEEDBACK = "feedback.jsonl"
METRICS = "metrics.jsonl"
RUN_CONFIG = "config.yaml"
SECRETS = (RESEARCHER_TOKEN, CODES_TXT)  # never in a download of the study's data

STEPS = ("consent", "instructions", "practice", "calibration", "teaching", "questionnaire", "done")
DECLINED = "declined"
FINAL_STEPS = ("done", DECLINED)


def is_study(directory: str | os.PathLike[str]) -> bool:
    """Whether ``directory`` holds a study (its ``study.json``)."""
    return (Path(directory) / STUDY_JSON).is_file()


def participant_dir(directory: str | os.PathLike[str], code: str) -> Path:
    """``<dir>/participants/<code>``."""
    return Path(directory) / PARTICIPANTS / code


def participant_json(directory: str | os.PathLike[str], code: str) -> Path:
    """``<dir>/participants/<code>/participant.json``."""
    return participant_dir(directory, code) / PARTICIPANT_JSON


def run_dir(directory: str | os.PathLike[str], code: str) -> Path:
    """The participant's train.py run directory."""
    return participant_dir(directory, code) / RUN


def relative_run_dir(code: str) -> str:
    """The run directory as participant.json records it (relative to the study directory)."""
    return f"{PARTICIPANTS}/{code}/{RUN}"


def worker_log(directory: str | os.PathLike[str], code: str) -> Path:
    """The worker's stdout and stderr."""
    return participant_dir(directory, code) / WORKER_LOG


def worker_pid(directory: str | os.PathLike[str], code: str) -> Path:
    """The pid of the participant's last worker."""
    return participant_dir(directory, code) / WORKER_PID


def _fsync_dir(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_atomic(path: str | os.PathLike[str], text: str, mode: int = 0o644) -> None:
    """Write ``text`` to ``path`` so that a crash leaves either the old file or the new one, never a part
    (a temporary file beside it, fsync'd, then ``os.replace``)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        os.fchmod(fd, mode)
        os.write(fd, text.encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    os.replace(tmp, path)
    _fsync_dir(path.parent)


def write_json(path: str | os.PathLike[str], value: Any, mode: int = 0o644) -> None:
    """``value`` as indented JSON, written atomically."""
    write_atomic(path, json.dumps(value, indent=2, sort_keys=True) + "\n", mode)


def read_json(path: str | os.PathLike[str]) -> Any:
    """The JSON value in ``path``."""
    return json.loads(Path(path).read_text())


def write_secret(path: str | os.PathLike[str], text: str) -> None:
    """A file only its owner can read (0600), written atomically."""
    write_atomic(path, text, 0o600)


def append_event(directory: str | os.PathLike[str], kind: str, **fields: Any) -> dict[str, Any]:
    """Append one line ``{"t", "event", ...fields}`` to ``events.jsonl`` and fsync it; returns the line."""
    record = {"t": round(time.time(), 3), "event": kind, **fields}
    fd = os.open(Path(directory) / EVENTS, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    try:
        os.write(fd, (json.dumps(record, sort_keys=True) + "\n").encode())
        os.fsync(fd)
    finally:
        os.close(fd)
    return record


def read_events(directory: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Every complete line of ``events.jsonl`` (a line cut short by a crash is left out)."""
    path = Path(directory) / EVENTS
    if not path.exists():
        return []
    events = []
    for line in path.read_text().splitlines():
        try:
            events.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return events


def read_study(directory: str | os.PathLike[str]) -> dict[str, Any]:
    """The study's resolved config (``study.json``)."""
    return read_json(Path(directory) / STUDY_JSON)


def participant_codes(directory: str | os.PathLike[str]) -> Iterator[str]:
    """The codes of every participant with a ``participant.json``."""
    root = Path(directory) / PARTICIPANTS
    if not root.is_dir():
        return
    for child in sorted(root.iterdir()):
        if (child / PARTICIPANT_JSON).is_file():
            yield child.name


def read_participants(directory: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """Every participant's record, in enrolment order (``index``), each with ``run_dir`` made absolute
    under ``run_path``."""
    records = []
    for code in participant_codes(directory):
        record = read_json(participant_json(directory, code))
        record["run_path"] = str(Path(directory) / record["run_dir"])
        records.append(record)
    return sorted(records, key=lambda r: r["index"])
