"""The study directory's names and the readers ``evaluate.py runs=<study dir>`` needs (docs/study.md).

EVAL's minimal copy, written to the spec's on-disk contract; the integrator merges it with the study
core's layout.py, which owns every name::

    <dir>/study.json                               the resolved study config
    <dir>/participants/<code>/participant.json     one participant's record
    <dir>/participants/<code>/run/                 their train.py run directory
"""

from __future__ import annotations

import json
from pathlib import Path

from hfrl_torch.common.errors import UserError

STUDY_FILE = "study.json"
PARTICIPANTS_DIR = "participants"
PARTICIPANT_FILE = "participant.json"
RUN_DIR = "run"
STEPS = ("consent", "instructions", "practice", "calibration", "teaching", "questionnaire", "done")
DECLINED = "declined"
RESULTS_DIR = "results"  # where evaluate.py runs=<study dir> writes its report by default


def is_study_dir(path: str | Path) -> bool:
    """Whether ``path`` holds a study (its ``study.json``), not run or multirun directories."""
    return (Path(path) / STUDY_FILE).is_file()


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path} is corrupt or unreadable: {str(exc).splitlines()[0]}") from exc
    if not isinstance(data, dict):
        raise UserError(f"{path} is corrupt: it holds a {type(data).__name__}, not a JSON object")
    return data


def read_study(study_dir: str | Path) -> dict:
    """The study's resolved config (``study.json``); one-line ``UserError`` naming the file if corrupt."""
    return _read_json(Path(study_dir) / STUDY_FILE)


def read_participants(study_dir: str | Path) -> list[dict]:
    """Every participant's record, in enrolment order; one-line ``UserError`` naming a corrupt file."""
    root = Path(study_dir) / PARTICIPANTS_DIR
    if not root.is_dir():
        return []
    out = []
    for path in sorted(root.glob(f"*/{PARTICIPANT_FILE}")):
        record = _read_json(path)
        for key in ("code", "step"):
            if not isinstance(record.get(key), str):
                raise UserError(f"{path} is corrupt: {key!r} is {record.get(key)!r}, must be a string")
        if record.get("condition") is not None and not isinstance(record["condition"], str):
            raise UserError(f"{path} is corrupt: 'condition' is {record['condition']!r}, must be a label")
        if not isinstance(record.get("index"), int) or isinstance(record.get("index"), bool):
            raise UserError(f"{path} is corrupt: 'index' is {record.get('index')!r}, must be an integer")
        out.append(record)
    return sorted(out, key=lambda r: r["index"])


def run_dir(study_dir: str | Path, record: dict) -> Path:
    """A participant's run directory: ``run_dir`` of their record (relative to the study) or the default."""
    rel = record.get("run_dir") or f"{PARTICIPANTS_DIR}/{record['code']}/{RUN_DIR}"
    return Path(study_dir) / rel
