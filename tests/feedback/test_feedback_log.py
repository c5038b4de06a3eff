"""The feedback log: round trip, sessions, a writer killed mid-way, and one-line errors for bad files."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import pytest

from hfrl_torch.common.errors import UserError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import DuplicateFeedbackWarning, FeedbackLog, FeedbackLogError, load_feedback_log

REPO = Path(__file__).resolve().parents[2]


def _ev(i: int, session: str = "") -> FeedbackEvent:
    return FeedbackEvent(
        time=1_700_000_000.0 + 0.137 * i,
        value=1.0 if i % 3 else -1.0,
        source="human:browser",
        session=session,
        step=i,
        episode=i // 4,
    )


def _write(path: Path, n: int, session: str = "s1") -> list[FeedbackEvent]:
    with FeedbackLog(path, session) as log:
        return [log.append(_ev(i)) for i in range(n)]


def test_round_trip_and_format(tmp_path):
    path = tmp_path / "fb" / "feedback.jsonl"
    written = _write(path, 6)
    assert load_feedback_log(path) == written
    assert all(e.session == "s1" for e in written)
    lines = path.read_text().splitlines()
    header = json.loads(lines[0])
    assert (header["schema"], header["version"], header["session"]) == ("hfrl_torch.feedback", 2, "s1")
    assert list(json.loads(lines[1])) == ["time", "step", "episode", "value", "source", "session", "seq"]
    assert [e.seq for e in written] == list(range(6)) and written[2].id == ("s1", 2)
    assert len(lines) == 7


def test_event_keeps_its_own_session_and_extend(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "s1") as log:
        log.append(_ev(0, session="other"))
        log.extend([_ev(1), _ev(2)])
        assert log.count == 3
    assert [e.session for e in load_feedback_log(path)] == ["other", "s1", "s1"]


def test_reopen_appends_a_new_session(tmp_path):
    path = tmp_path / "f.jsonl"
    first = _write(path, 3, session="morning")
    with FeedbackLog(path, "evening") as log:
        second = [log.append(_ev(i)) for i in range(3, 5)]
    assert load_feedback_log(path) == first + second
    headers = [json.loads(x) for x in path.read_text().splitlines() if "schema" in x]
    assert [h["session"] for h in headers] == ["morning", "evening"]


def test_writes_after_close_fail(tmp_path):
    log = FeedbackLog(tmp_path / "f.jsonl", "s")
    log.close()
    log.close()
    with pytest.raises(ValueError, match="closed"):
        log.append(_ev(0))


def test_truncated_last_line(tmp_path):
    path = tmp_path / "f.jsonl"
    written = _write(path, 4)
    data = path.read_bytes()
    path.write_bytes(data[:-9])
    with pytest.raises(FeedbackLogError, match=r"f\.jsonl:5: truncated") as info:
        load_feedback_log(path)
    assert isinstance(info.value, UserError)
    assert info.value.events == written[:3]
    assert info.value.line == 5 and info.value.truncated
    events, err = load_feedback_log(path, strict=False)
    assert events == written[:3]
    assert err is not None and err.line == 5


def test_last_line_without_newline_but_complete_is_kept(tmp_path):
    path = tmp_path / "f.jsonl"
    written = _write(path, 2)
    path.write_bytes(path.read_bytes().rstrip(b"\n"))
    assert load_feedback_log(path) == written


def test_garbage_line_in_the_middle(tmp_path):
    path = tmp_path / "f.jsonl"
    written = _write(path, 5)
    lines = path.read_bytes().splitlines(keepends=True)
    lines.insert(3, b"\x00\x17 not json at all\n")
    path.write_bytes(b"".join(lines))
    with pytest.raises(FeedbackLogError, match=r"f\.jsonl:4: corrupt") as info:
        load_feedback_log(path)
    assert info.value.events == written[:2]
    assert not info.value.truncated
    assert "\n" not in str(info.value)
    events, err = load_feedback_log(path, strict=False)
    assert events == written[:2] and err is not None and err.line == 4


_LINE = '{"time": 1.0, "step": 0, "episode": 0, "source": "x", "session": "s", %s}'


@pytest.mark.parametrize(
    ("bad_line", "match"),
    [
        ('{"time": 1.0, "step": 0, "episode": 0, "value": 1.0, "source": "x"}', "missing session"),
        (_LINE % '"value": 1.0', "missing seq"),
        (_LINE % '"value": NaN, "seq": 0', "NaN"),
        (_LINE % '"value": 5000, "seq": 0', "value"),
        (_LINE % '"value": 1, "seq": -1', "seq=-1"),
        ("[1, 2, 3]", "not a JSON object"),
        ("", "corrupt"),
    ],
)
def test_invalid_event_lines(tmp_path, bad_line, match):
    path = tmp_path / "f.jsonl"
    written = _write(path, 2)
    with open(path, "a") as f:
        f.write(bad_line + "\n")
        f.write(json.dumps(_ev(9, "s1").to_dict()) + "\n")
    with pytest.raises(FeedbackLogError, match=rf"f\.jsonl:4: .*{match}") as info:
        load_feedback_log(path)
    assert info.value.events == written


def test_wrong_version_schema_missing_and_empty(tmp_path):
    path = tmp_path / "f.jsonl"
    path.write_text(json.dumps({"schema": "hfrl_torch.feedback", "version": 3, "session": "s"}) + "\n")
    with pytest.raises(FeedbackLogError, match=r":1: feedback log version 3; this build reads 1 and 2"):
        load_feedback_log(path)
    path.write_text(json.dumps({"schema": "hfrl_torch.feedback", "version": True, "session": "s"}) + "\n")
    with pytest.raises(FeedbackLogError, match=r"f\.jsonl:1: feedback log version True"):
        load_feedback_log(path)
    path.write_text(json.dumps({"schema": "something.else", "version": 1}) + "\n")
    with pytest.raises(FeedbackLogError, match="not a feedback log"):
        load_feedback_log(path)
    path.write_text(json.dumps(_ev(0, "s").to_dict()) + "\n")
    with pytest.raises(FeedbackLogError, match="not a feedback log"):
        load_feedback_log(path)
    with pytest.raises(FeedbackLogError, match="does not exist"):
        load_feedback_log(tmp_path / "nope.jsonl")
    events, err = load_feedback_log(tmp_path / "nope.jsonl", strict=False)
    assert events == [] and err is not None
    path.write_bytes(b"")
    with pytest.raises(FeedbackLogError, match="empty file"):
        load_feedback_log(path)


def test_wrong_version_in_a_later_session_header(tmp_path):
    path = tmp_path / "f.jsonl"
    written = _write(path, 2)
    with open(path, "a") as f:
        f.write(json.dumps({"schema": "hfrl_torch.feedback", "version": 7, "session": "x"}) + "\n")
    with pytest.raises(FeedbackLogError, match=r":4: feedback log version 7") as info:
        load_feedback_log(path)
    assert info.value.events == written


def test_reopen_repairs_an_interrupted_last_line(tmp_path):
    path = tmp_path / "f.jsonl"
    written = _write(path, 3)
    path.write_bytes(path.read_bytes()[:-20])
    with pytest.warns(UserWarning, match="incomplete last line"), FeedbackLog(path, "s2") as log:
        more = log.append(_ev(10))
    assert load_feedback_log(path) == [*written[:2], more]


def test_reopen_refuses_a_corrupt_log(tmp_path):
    path = tmp_path / "f.jsonl"
    _write(path, 3)
    lines = path.read_bytes().splitlines(keepends=True)
    lines.insert(2, b"garbage\n")
    path.write_bytes(b"".join(lines))
    before = path.read_bytes()
    with pytest.raises(FeedbackLogError, match="will not append"):
        FeedbackLog(path, "s2")
    assert path.read_bytes() == before
    other = tmp_path / "not_a_log.txt"
    other.write_bytes(b"hello")
    with pytest.raises(FeedbackLogError, match="will not append"):
        FeedbackLog(other, "s2")
    assert other.read_bytes() == b"hello"


_CHILD = textwrap.dedent(
    """
    import sys
    from hfrl_torch.feedback.events import FeedbackEvent
    from hfrl_torch.feedback.log import FeedbackLog

    log = FeedbackLog(sys.argv[1], "crash")
    i = 0
    while True:
        log.append(FeedbackEvent(time=1000.0 + i, value=1.0, source="simulated:oracle", step=i, episode=0))
        print(i, flush=True)
        i += 1
    """
)


def test_writer_killed_midway_loses_nothing_it_confirmed(tmp_path):
    path = tmp_path / "f.jsonl"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.Popen(
        [sys.executable, "-c", _CHILD, str(path)], stdout=subprocess.PIPE, text=True, env=env, cwd=REPO
    )
    confirmed = -1
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            confirmed = int(line)
            if confirmed >= 40:
                break
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert confirmed >= 40
    events, err = load_feedback_log(path, strict=False)
    assert err is None or err.truncated
    assert len(events) >= confirmed + 1
    assert [e.step for e in events] == list(range(len(events)))
    assert [e.seq for e in events] == list(range(len(events)))
    assert all(e.session == "crash" for e in events)


_EVENT = '{"time": 1.0, "step": 0, "episode": 0, "value": %s, "source": "x", "session": "s1", "seq": 9}'


@pytest.mark.parametrize(
    ("bad_line", "match"),
    [
        (_EVENT % ("9" * 400), r"corrupt line \(an integer of 400 digits; allowed: at most 18\)"),
        (_EVENT.replace('"step": 0', '"step": ' + "1" * 30) % "1", "an integer of 30 digits"),
        (_EVENT % ("1." + "5" * 60), "a number of 62 characters; allowed: at most 40"),
        (_EVENT % "1e400", "value must be a finite number"),
        (_EVENT % "Infinity", r"corrupt line \(Infinity; allowed: finite numbers\)"),
        (_EVENT % "-Infinity", r"-Infinity; allowed"),
        ("[" * 5000 + "]" * 5000, r"corrupt line \(nested 5000 deep; allowed: at most 16\)"),
        ('{"a": ' * 2000 + "1" + "}" * 2000, "nested 2000 deep"),
        ('{"pad": "' + "x" * 100_000 + '"}', r"corrupt line \(longer than 16384 bytes\)"),
        (_EVENT.replace('"x"', '"\\ud800"') % "1", None),  # a lone surrogate is a valid JSON string
        (_EVENT % "1" + "}", r"corrupt line \(not JSON\)"),
        (_EVENT.replace('"time": 1.0', '"time": true') % "1", "time must be finite"),
        (_EVENT.replace('"source": "x"', '"source": 7') % "1", "source must be a non-empty string"),
    ],
)
def test_hostile_lines_give_feedback_log_errors_only(tmp_path, bad_line, match):
    path = tmp_path / "f.jsonl"
    written = _write(path, 2)
    with open(path, "a") as f:
        f.write(bad_line + "\n")
    if match is None:
        assert len(load_feedback_log(path)) == 3
        return
    with pytest.raises(FeedbackLogError, match=rf"f\.jsonl:4: .*{match}") as info:
        load_feedback_log(path)
    assert info.value.events == written and "\n" not in str(info.value)
    events, err = load_feedback_log(path, strict=False)
    assert events == written and err is not None and err.line == 4 and not err.truncated


def test_random_garbage_lines_never_raise_anything_but_feedback_log_errors(tmp_path):
    path = tmp_path / "f.jsonl"
    written = _write(path, 3)
    good = path.read_bytes()
    sample = json.dumps({**_ev(7, "s1").to_dict(), "seq": 7}).encode()
    pieces = [b"[", b"{", b"]", b"}", b'"', b"\\", b"9" * 50, b"NaN", b"-", b"e", b".", b",", b":", b"\xc3"]
    rng = random.Random(6)
    outcomes = set()
    for _ in range(500):
        line = bytearray(sample)
        for _ in range(rng.randint(1, 6)):
            at = rng.randrange(len(line) + 1)
            if rng.random() < 0.5:
                line[at:at] = rng.choice(pieces) * rng.randint(1, 40)
            elif line:
                line[min(at, len(line) - 1)] = rng.randrange(256)
        path.write_bytes(good + bytes(line) + b"\n" + sample + b"\n")
        with warnings.catch_warnings():  # a mutation may leave the line a copy of the next
            warnings.simplefilter("ignore", DuplicateFeedbackWarning)
            events, err = load_feedback_log(path, strict=False)  # anything else raised fails the test
        assert events[:3] == written and len(events) <= 5
        outcomes.add(err is None)
        if err is not None:
            assert err.line == 5 and str(path) in str(err) and "\n" not in str(err)
    assert outcomes == {True, False}


def test_the_writer_refuses_lines_the_reader_would_refuse(tmp_path):
    path = tmp_path / "f.jsonl"
    with FeedbackLog(path, "s1") as log, pytest.raises(ValueError, match="too long; allowed: at most 16384"):
        log.append(FeedbackEvent(time=1.0, value=1.0, source="x" * 20_000))
    with pytest.raises(ValueError, match="too long"):
        FeedbackLog(tmp_path / "g.jsonl", "s" * 20_000)
    assert not (tmp_path / "g.jsonl").exists()
    assert load_feedback_log(path) == []
