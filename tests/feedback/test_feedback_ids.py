"""Stable event ids (session, seq): assigned by the log, continued on reopen, duplicates dropped on read,
and a rewound log that takes the events a resumed trainer gives again without writing them twice."""

from __future__ import annotations

import json
import warnings

import pytest

from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import (
    DuplicateFeedbackWarning,
    FeedbackLog,
    load_feedback_log,
    read_feedback_log,
)


def _ev(i: int, session: str = "", value: float | None = None) -> FeedbackEvent:
    v = (1.0 if i % 3 else -1.0) if value is None else value
    return FeedbackEvent(time=1000.0 + 0.5 * i, value=v, source="simulated:oracle", session=session, step=i)


def _v1_log(path, segments: list[list[FeedbackEvent]], session: str = "run") -> None:
    """A log as version 1 wrote it: one header per (re)opening, events without seq."""
    lines = []
    for events in segments:
        lines.append({"schema": "hfrl_torch.feedback", "version": 1, "session": session, "created": 1.0})
        for ev in events:
            d = ev.to_dict()
            del d["seq"]
            lines.append({**d, "session": ev.session or session})
    path.write_text("".join(json.dumps(x) + "\n" for x in lines))


def test_the_constructor_keeps_its_arguments_and_seq_defaults_to_unlogged():
    ev = FeedbackEvent(1.0, -1.0, "human:browser", "s", 4, 2)
    assert (ev.session, ev.step, ev.episode, ev.seq, ev.id) == ("s", 4, 2, -1, None)
    assert FeedbackEvent(time=1.0, value=1.0, source="x", session="s", seq=3).id == ("s", 3)
    for bad in (-2, 1.5, True):
        with pytest.raises(ValueError, match=r"FeedbackEvent\.seq must be an integer"):
            FeedbackEvent(time=1.0, value=1.0, source="x", seq=bad)


def test_seq_counts_per_session_and_the_log_alone_assigns_it(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "run") as log:
        a = log.extend([_ev(0), _ev(1, "run/board1"), _ev(2)])
        b = log.append(FeedbackEvent(time=5.0, value=1.0, source="replay", seq=77))  # a replayed event's seq
    assert [(e.session, e.seq) for e in [*a, b]] == [("run", 0), ("run/board1", 0), ("run", 1), ("run", 2)]
    assert load_feedback_log(path) == [*a, b]
    assert read_feedback_log(path).last_seq == {"run": 2, "run/board1": 0}


def test_reopening_continues_each_session_after_its_largest_seq(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "run") as log:
        log.extend([_ev(0), _ev(1), _ev(2, "run/board1")])
    with FeedbackLog(path, "run") as log:
        assert log.last_seq == {"run": 1, "run/board1": 0}
        more = log.extend([_ev(3), _ev(4, "run/board1"), _ev(5, "other")])
    assert [e.id for e in more] == [("run", 2), ("run/board1", 1), ("other", 0)]
    events = load_feedback_log(path)
    assert len(events) == 6 and len({e.id for e in events}) == 6


def test_version_1_logs_are_read_and_reopened(tmp_path):
    path = tmp_path / "f.jsonl"
    _v1_log(path, [[_ev(0), _ev(1)]])
    old = load_feedback_log(path)
    assert [e.seq for e in old] == [-1, -1] and old[1].session == "run"
    with FeedbackLog(path, "run") as log:
        assert log.last_seq == {}
        new = log.append(_ev(2))
    assert new.id == ("run", 0)
    assert load_feedback_log(path) == [*old, new]
    assert [json.loads(x).get("version") for x in path.read_text().splitlines()] == [1, None, None, 2, None]


def test_a_version_1_resume_that_logged_an_iteration_again_is_deduplicated(tmp_path):
    """What a resumed run wrote before ids: the killed iteration's events again, under a new header."""
    path = tmp_path / "f.jsonl"
    first = [_ev(i) for i in range(6)]
    twice = [_ev(0, value=1.0), _ev(0, value=1.0)]  # two presses on one placement: both real
    _v1_log(path, [[*first, *twice], [*first[3:], *twice, _ev(6), _ev(7)]])
    with pytest.warns(DuplicateFeedbackWarning, match=r"f\.jsonl: dropped 5 duplicate feedback events"):
        events = load_feedback_log(path)
    assert [e.step for e in events] == [0, 1, 2, 3, 4, 5, 0, 0, 6, 7]
    contents = read_feedback_log(path)
    assert contents.duplicates == 5 and contents.error is None and contents.events == events


def test_an_event_logged_twice_under_one_id_is_read_once(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "run") as log:
        log.extend([_ev(0), _ev(1), _ev(2)])
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join([*lines, lines[2], lines[2]]))  # a replayed append of seq 1
    with pytest.warns(DuplicateFeedbackWarning, match="dropped 2 duplicate"):
        events = load_feedback_log(path)
    assert [e.seq for e in events] == [0, 1, 2]
    events, err = load_feedback_log(path.with_name("nope.jsonl"), strict=False)
    assert events == [] and err is not None and err.duplicates == 0


def test_no_warning_without_duplicates(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "run") as log:
        log.extend([_ev(0), _ev(0)])  # equal presses in one session are kept
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(load_feedback_log(path)) == 2


def _trainer(start: int, n: int) -> list[FeedbackEvent]:
    """A deterministic simulated trainer: the same events from the same state."""
    return [_ev(i) for i in range(start, start + n)]


def test_a_rewound_log_writes_each_event_once_across_a_kill(tmp_path):
    path = tmp_path / "f.jsonl"
    log = FeedbackLog(path, "run")
    log.extend(_trainer(0, 6))
    checkpoint = log.last_seq  # the learner has seen events 0..5
    log.extend(_trainer(6, 4))  # logged (write-ahead), then the run is killed before the next checkpoint
    del log
    resumed = FeedbackLog(path, "run")
    assert resumed.rewind(checkpoint) == 4
    again = resumed.extend(_trainer(6, 7))  # the restored trainer gives 6..9 again, then 10..12
    resumed.close()
    assert [e.seq for e in again] == list(range(6, 13)) and resumed.matched == 4 and resumed.count == 3
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        events = load_feedback_log(path)
    assert [e.step for e in events] == list(range(13)) and [e.seq for e in events] == list(range(13))


def test_rewinding_to_a_checkpoint_the_log_outran_never_loses_what_was_logged(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "run") as log:
        log.extend(_trainer(0, 5))
    with FeedbackLog(path, "run") as log:
        log.rewind({"run": 1})
        with pytest.warns(UserWarning, match="event 3 of session 'run', given again after a resume, differs"):
            out = log.extend([_ev(2), _ev(3, value=0.5), _ev(4)])
    assert [e.seq for e in out] == [2, 5, 6]
    lines = [json.loads(x) for x in path.read_text().splitlines() if "schema" not in x]
    assert [(x["seq"], x["step"], x["value"]) for x in lines][-3:] == [(4, 4, 1.0), (5, 3, 0.5), (6, 4, 1.0)]
    with pytest.warns(DuplicateFeedbackWarning, match="dropped 1 duplicate"):  # seq 6 says what seq 4 said
        events = load_feedback_log(path)
    assert [(e.seq, e.step) for e in events] == [(0, 0), (1, 1), (2, 2), (3, 3), (4, 4), (5, 3)]


def test_a_persons_unlearned_presses_are_read_back_not_given_again(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "run") as log:
        log.extend(_trainer(0, 5))
        checkpoint = log.last_seq
        log.extend(_trainer(5, 2))
    with FeedbackLog(path, "run") as log:
        unlearned = log.logged_after(checkpoint)
        assert [e.seq for e in unlearned] == [5, 6]
        assert log.append(_ev(9)).seq == 7  # no rewind: new presses continue after the log's end


def test_a_checkpoint_ahead_of_the_log_continues_after_the_checkpoint(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "run", fsync=False) as log:
        log.extend(_trainer(0, 3))
    with FeedbackLog(path, "run") as log:
        ahead = "has seen events up to 5 of session 'run' but the log ends at 2"
        with pytest.warns(UserWarning, match=ahead):
            assert log.rewind({"run": 5}) == 0
        assert log.append(_ev(6)).seq == 6
        with pytest.raises(ValueError, match="must be an integer >= -1"):
            log.rewind({"run": -3})
