"""What the study server's tests share: a small study config, the fake worker, waiting for a condition."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from hfrl_torch.study.config import StudyConfig

FAKE_TRAIN = Path(__file__).parent / "fake_train.py"  # a worker that starts at once and imports nothing
LABELS = ("tetris_a", "tetris_b", "keepaway_a")


def study_config(tmp_path: Path, **over: object) -> StudyConfig:
    """A small study: three conditions, a two-trial calibration and a two-item questionnaire."""
    node = {
        "name": "t",
        "dir": str(tmp_path / "study"),
        "title": "Teach an agent",
        "consent": "Plain words about the study.",
        "instructions": "Press Good or Bad.",
        "practice_s": 5,
        "calibration": {"trials": 2, "optional": True},
        "questionnaire": [
            {
                "id": "effort",
                "kind": "likert",
                "text": "It took effort.",
                "points": 5,
                "low": "no",
                "high": "yes",
            },
            {"id": "comments", "kind": "text", "text": "Anything else?", "max_chars": 50},
        ],
        "conditions": [{"label": label, "overrides": [f"seed_note={label}"]} for label in LABELS],
        **over,
    }
    return StudyConfig.from_node(node)


def wait_for(condition: Callable[[], object], timeout: float = 15.0) -> None:
    """Return once ``condition()`` is true; fail after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)
