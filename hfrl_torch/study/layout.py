"""The study directory on disk: the names and readers ``evaluate.py runs=<study dir>`` needs.

EVAL's subset of the study core's layout.py (branch ``study``): the same names and functions, copied as
they are there, plus ``RESULTS``, where evaluate.py writes a study's report. The layout::

    <dir>/study.json                 the resolved study config
    <dir>/participants/<code>/participant.json
    <dir>/participants/<code>/run/   the participant's train.py run directory
    <dir>/results/                   evaluate.py runs=<dir>: the report (summary.md, CSVs, plots)
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

STUDY_JSON = "study.json"
PARTICIPANTS = "participants"
PARTICIPANT_JSON = "participant.json"
RUN = "run"
RESULTS = "results"  # EVAL's addition: evaluate.py's default ``out`` for a study

STEPS = ("consent", "instructions", "practice", "calibration", "teaching", "questionnaire", "done")
DECLINED = "declined"


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


def read_json(path: str | os.PathLike[str]) -> Any:
    """The JSON value in ``path``."""
    return json.loads(Path(path).read_text())


def participant_codes(directory: str | os.PathLike[str]) -> Iterator[str]:
    """The codes of every participant with a ``participant.json``."""
    root = Path(directory) / PARTICIPANTS
    if not root.is_dir():
        return
    for child in sorted(root.iterdir()):
        if (child / PARTICIPANT_JSON).is_file():
            yield child.name
