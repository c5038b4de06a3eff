"""Feedback events of one step as tensordict entries: value, time, source."""

from __future__ import annotations

import math

from hfrl_torch import keys
from hfrl_torch.feedback.events import SOURCE_KINDS, FeedbackEvent, feedback_tensors, source_kind


def test_events_become_value_time_and_source_per_board():
    events = [
        [],
        [FeedbackEvent(time=1.5, value=1.0, source="simulated:oracle")],
        [
            FeedbackEvent(time=2.0, value=-1.0, source="human:browser"),
            FeedbackEvent(time=2.5, value=1.0, source="replay"),
        ],
    ]
    t = feedback_tensors(events)
    assert t[keys.FEEDBACK].shape == (3, 1)
    assert t[keys.FEEDBACK].view(-1).tolist() == [0.0, 1.0, 0.0]
    when = t[keys.FEEDBACK_TIME].view(-1).tolist()
    assert math.isnan(when[0]) and when[1:] == [1.5, 2.5]
    kinds = [SOURCE_KINDS[k] for k in t[keys.FEEDBACK_SOURCE].view(-1).tolist()]
    assert kinds == ["none", "simulated", "replay"]


def test_unknown_sources_are_other():
    assert SOURCE_KINDS[source_kind("robot:arm")] == "other"
    assert SOURCE_KINDS[source_kind("human")] == "human"
