"""Fixtures of the study tests: a small valid study config."""

from __future__ import annotations

import copy
from typing import Any

import pytest

BASE: dict[str, Any] = {
    "name": "t",
    "dir": "studies/t",
    "title": "A test study",
    "consent": "We record your presses.",
    "instructions": "Press Good or Bad.",
    "port": 0,
    "max_participants": 8,
    "calibration": {"trials": 4, "optional": True},
    "questionnaire": [
        {
            "id": "effort",
            "kind": "likert",
            "text": "It took effort.",
            "points": 5,
            "low": "no",
            "high": "yes",
        },
        {"id": "comments", "kind": "text", "text": "Anything else?", "max_chars": 20},
    ],
    "common": ["trainer.wait_for_page_s=0"],
    "conditions": [
        {"label": "tetris_a", "overrides": ["domain=tetris"]},
        {"label": "keepaway_b", "overrides": ["domain=keepaway"]},
    ],
}


@pytest.fixture
def raw() -> dict[str, Any]:
    """A fresh copy of a valid study config (a plain mapping) to spoil."""
    return copy.deepcopy(BASE)
