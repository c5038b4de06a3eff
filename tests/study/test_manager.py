"""The Study manager with a stand-in for train.py (tests/study/fake_train.py): every step, the design's
blinding, enrolment limits, stop/resume, crashes and reopening a study."""

from __future__ import annotations

import json
import stat
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.study import layout
from hfrl_torch.study.config import StudyConfig
from hfrl_torch.study.manager import MAX_RESTARTS, JoinRefused, StepConflict, Study, StudyFull

FAKE = Path(__file__).with_name("fake_train.py")
CREDITS = {"tetris_a": "previous_step", "keepaway_b": "gamma"}


@pytest.fixture
def opened(tmp_path: Path) -> Iterator[list[Study]]:
    studies: list[Study] = []
    yield studies
    for study in studies:
        study.close(timeout=5)


def _open(raw: dict[str, Any], tmp_path: Path, opened: list[Study], **changes: Any) -> Study:
    study = Study.open(
        StudyConfig.from_node({**raw, **changes}), tmp_path / "s", train_script=FAKE, credits=CREDITS
    )
    opened.append(study)
    return study


def _until(study: Study, done: Callable[[], bool], timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, "timed out"
        study.poll()
        time.sleep(0.02)


def _argv(study: Study, code: str) -> list[list[str]]:
    path = study.directory / "participants" / code / "run" / "argv.jsonl"
    return [json.loads(line) for line in path.read_text().splitlines()]


def _to_teaching(study: Study, code: str, delays: list[float] | None = None) -> None:
    study.advance(code, "consent", "agree", {})
    study.advance(code, "instructions", "next", {})
    study.advance(code, "practice", "next", {})
    if delays is None:
        study.advance(code, "calibration", "skip", {})
    else:
        study.advance(code, "calibration", "next", {"delays_s": delays})


def test_every_step_and_the_condition_never_shown(
    raw: dict[str, Any], tmp_path: Path, opened: list[Study]
) -> None:
    study = _open(raw, tmp_path, opened)
    p = study.join(simulated=True)
    states = [study.state(p.code)]
    assert states[0]["step"] == "consent" and states[0]["teaching"]["url"] == f"/p/{p.code}/teach/"
    states.append(study.advance(p.code, "consent", "agree", {}))
    states.append(study.advance(p.code, "instructions", "next", {}))
    states.append(study.advance(p.code, "practice", "next", {}))
    assert states[-1]["step"] == "calibration"
    states.append(study.advance(p.code, "calibration", "next", {"delays_s": [0.3, 0.5, 0.4, 0.45]}))
    assert states[-1]["step"] == "teaching"
    _until(study, lambda: study.teaching_endpoint(p.code) is not None)
    states.append(study.state(p.code))
    assert states[-1]["teaching"]["ready"] is True
    with pytest.raises(ValueError, match="still going"):
        study.advance(p.code, "teaching", "next", {})
    (study.directory / "participants" / p.code / "finish").touch()  # the budget spent / Finish and save
    _until(study, lambda: study.state(p.code)["step"] == "questionnaire")
    states.append(study.state(p.code))
    assert states[-1]["summary"] == {"presses": 3} and states[-1]["ended"] == "finished"
    states.append(
        study.advance(p.code, "questionnaire", "next", {"answers": {"effort": 4, "comments": "ok"}})
    )
    assert states[-1]["step"] == "done"
    for state in states:
        text = json.dumps(state)
        assert "tetris_a" not in text and "keepaway_b" not in text and "condition" not in text
    record = layout.read_json(layout.participant_json(study.directory, p.code))
    assert record["step"] == "done" and record["simulated"] is True and record["answers"]["effort"] == 4
    assert record["condition"] in CREDITS and record["run_dir"] == f"participants/{p.code}/run"
    assert record["calibration"]["reaction_s"] == 0.425
    times = [record["steps"][step] for step in layout.STEPS]  # every step entered, in order
    assert times == sorted(times)
    argv = _argv(study, p.code)[0]
    assert (
        "trainer=interactive" in argv
        and "trainer.reaction_s=0.425" in argv
        and "trainer.wait_for_page_s=0" in argv
    )
    assert f"seed={p.index}" in argv and any(a.startswith("trainer.token=") for a in argv)
    assert any(a.startswith("human.gamma_shape=") for a in argv) == (record["condition"] == "keepaway_b")
    events = [e["event"] for e in layout.read_events(study.directory)]
    assert events[:2] == ["created", "enrolled"] and "worker_start" in events and "worker_exit" in events


def test_gamma_fit_only_for_gamma_credit(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    study = _open(raw, tmp_path, opened)
    seen = {}
    for _ in range(2):  # the first block holds both conditions
        p = study.join(simulated=False)
        _to_teaching(study, p.code, [0.3, 0.5, 0.4, 0.45])
        _until(study, lambda p=p: (study.directory / p.run_dir / "argv.jsonl").exists())
        seen[p.condition] = _argv(study, p.code)[0]
    assert any(a.startswith("human.gamma_scale=") for a in seen["keepaway_b"])
    assert not any(a.startswith("human.gamma") for a in seen["tetris_a"])
    assert all("trainer.reaction_s=0.425" in argv for argv in seen.values())


def test_decline_keeps_the_record_only(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    study = _open(raw, tmp_path, opened)
    p = study.join(simulated=False)
    state = study.advance(p.code, "consent", "decline", {})
    assert state["step"] == "declined" and state["ended"] == "declined"
    with pytest.raises(ValueError, match="allowed: -"):
        study.advance(p.code, "declined", "next", {})
    assert not (study.directory / p.run_dir).exists()


def test_calibration_skip_and_off(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    study = _open(raw, tmp_path, opened, calibration={"trials": 4, "optional": False})
    p = study.join(simulated=False)
    for step, action in (("consent", "agree"), ("instructions", "next"), ("practice", "next")):
        study.advance(p.code, step, action, {})
    with pytest.raises(ValueError, match="cannot be skipped"):
        study.advance(p.code, "calibration", "skip", {})
    with pytest.raises(ValueError, match=r"data\.delays_s is missing"):
        study.advance(p.code, "calibration", "next", {})
    with pytest.raises(ValueError, match=r"delays_s\[0\]=9 is invalid"):
        study.advance(p.code, "calibration", "next", {"delays_s": [9]})
    assert study.state(p.code)["step"] == "calibration"
    study.close()
    opened.clear()
    skipping = _open(raw, tmp_path / "b", opened)
    q = skipping.join(simulated=False)
    _to_teaching(skipping, q.code)
    assert skipping.state(q.code)["step"] == "teaching" and skipping.get(q.code).calibration is None
    _until(skipping, lambda: (skipping.directory / q.run_dir / "argv.jsonl").exists())
    assert not any(a.startswith("trainer.reaction_s") for a in _argv(skipping, q.code)[0])
    off = _open(raw, tmp_path / "c", opened, calibration={"trials": 0, "optional": True})
    r = off.join(simulated=False)
    for step, action in (("consent", "agree"), ("instructions", "next")):
        off.advance(r.code, step, action, {})
    assert off.advance(r.code, "practice", "next", {})["step"] == "teaching"


def test_stale_step_and_bad_data(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    study = _open(raw, tmp_path, opened)
    p = study.join(simulated=False)
    study.advance(p.code, "consent", "agree", {})
    with pytest.raises(StepConflict) as info:
        study.advance(p.code, "consent", "agree", {})  # a reloaded page sends its step again
    assert info.value.state["step"] == "instructions"
    with pytest.raises(ValueError, match="action='agree' is invalid at step 'instructions'; allowed: next"):
        study.advance(p.code, "instructions", "agree", {})
    with pytest.raises(ValueError, match="data key 'x' is invalid here"):
        study.advance(p.code, "instructions", "next", {"x": 1})
    with pytest.raises(KeyError):
        study.advance("AAAAAAAAAAAA", "consent", "agree", {})
    assert study.get("nonsense") is None and study.get(p.code.lower()) is p
    _to_q = [("instructions", "next"), ("practice", "next"), ("calibration", "skip")]
    for step, action in _to_q:
        study.advance(p.code, step, action, {})
    (study.directory / "participants" / p.code / "finish").touch()
    _until(study, lambda: study.state(p.code)["step"] == "questionnaire")
    for answers, message in (
        ({"effort": 6}, r"answers.effort=6 is invalid: must be an integer 1..5"),
        ({"effort": True}, "answers.effort=True is invalid"),
        ({"comments": "x" * 21}, "answers.comments is invalid: must be text of at most 20 characters"),
        ({"age": 3}, "answers has no item 'age'"),
        ([1], "data.answers must be an object"),
    ):
        with pytest.raises(ValueError, match=message):
            study.advance(p.code, "questionnaire", "next", {"answers": answers})
    state = study.advance(p.code, "questionnaire", "next", {"answers": {"effort": None}})
    assert state["step"] == "done" and study.get(p.code).answers == {}


def test_enrollment_limits(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    study = _open(raw, tmp_path, opened, max_participants=2)
    study.join(simulated=False)
    study.join(simulated=False)
    with pytest.raises(StudyFull, match="the study is full"):
        study.join(simulated=False)
    coded = _open(raw, tmp_path / "codes", opened, enrollment="codes", codes=3)
    with pytest.raises(JoinRefused, match="by their codes only"):
        coded.join(simulated=False)
    codes_txt = coded.directory / layout.CODES_TXT
    assert stat.S_IMODE(codes_txt.stat().st_mode) == 0o600
    codes = codes_txt.read_text().split()
    assert len(codes) == 3 and codes == coded.premade_codes
    p = coded.get(codes[1])
    assert p is not None and p.index == 0 and coded.get(codes[1]) is p and coded.get(codes[0]).index == 1
    token = coded.directory / layout.RESEARCHER_TOKEN
    assert stat.S_IMODE(token.stat().st_mode) == 0o600 and token.read_text().strip() == coded.researcher_token


def test_stop_resume_and_crash_restarts(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    study = _open(raw, tmp_path, opened)
    p = study.join(simulated=False)
    _to_teaching(study, p.code)
    _until(study, lambda: study.teaching_endpoint(p.code) is not None)
    study.stop(p.code)
    assert study.state(p.code)["stopped"] is True and study.teaching_endpoint(p.code) is None
    _until(study, lambda: study.overview()[0]["worker"] == "none")
    assert study.state(p.code)["step"] == "teaching"  # stopped by the study: not finished
    study.resume(p.code)
    _until(study, lambda: study.teaching_endpoint(p.code) is not None)
    fresh, resumed = _argv(study, p.code)
    assert any(a.startswith("resume=") for a in resumed)
    # both workers are blind: no message of the run names the participant's condition
    assert "trainer.blind=true" in fresh and "trainer.blind=true" in resumed
    crash = study.directory / "participants" / p.code / "crash"
    crash.touch()
    _until(study, lambda: study.state(p.code)["step"] == "questionnaire")
    assert study.state(p.code)["ended"] == "the run failed (exit status 1)"
    assert len(_argv(study, p.code)) == 2 + MAX_RESTARTS
    exits = [e for e in layout.read_events(study.directory) if e["event"] == "worker_exit"]
    assert [e["by"] for e in exits] == ["study"] + ["crash"] * (1 + MAX_RESTARTS)


def test_reopen_resumes_and_refuses_other_config(
    raw: dict[str, Any], tmp_path: Path, opened: list[Study]
) -> None:
    study = _open(raw, tmp_path, opened)
    teaching, consenting = study.join(simulated=False), study.join(simulated=True)
    _to_teaching(study, teaching.code)
    study.advance(consenting.code, "consent", "agree", {})
    _until(study, lambda: study.teaching_endpoint(teaching.code) is not None)
    token = study.researcher_token
    study.close()
    opened.clear()
    with pytest.raises(ConfigError, match=r"holds a study with another config \(conditions: saved"):
        _open(raw, tmp_path, opened, conditions=[{"label": "tetris_a", "overrides": ["domain=tetris"]}])
    again = _open(raw, tmp_path, opened, port=1234)  # the port may change
    assert again.researcher_token == token
    assert again.state(consenting.code)["step"] == "instructions" and again.get(consenting.code).simulated
    assert again.get(teaching.code).condition == teaching.condition
    _until(again, lambda: again.teaching_endpoint(teaching.code) is not None)
    argv = _argv(again, teaching.code)
    assert len(argv) == 2 and argv[1][0].startswith("resume=") and "trainer.host=127.0.0.1" not in argv[1]
    third = again.join(simulated=False)
    assert third.index == 2


def test_run_without_checkpoint_is_set_aside(
    raw: dict[str, Any], tmp_path: Path, opened: list[Study]
) -> None:
    study = _open(raw, tmp_path, opened)
    p = study.join(simulated=False)
    study.advance(p.code, "consent", "agree", {})
    study.advance(p.code, "instructions", "next", {})
    study.advance(p.code, "practice", "next", {})
    run = study.directory / p.run_dir
    run.mkdir(parents=True)
    (run / "config.yaml").write_text("a run killed while it started\n")
    study.advance(p.code, "calibration", "skip", {})
    _until(study, lambda: study.teaching_endpoint(p.code) is not None)
    aside = [d.name for d in run.parent.iterdir() if d.name.startswith("run.unfinished-")]
    assert len(aside) == 1 and (run.parent / aside[0] / "config.yaml").exists()
    assert not any(a.startswith("resume=") for a in _argv(study, p.code)[0])


def test_worker_outlives_the_calling_thread(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    """A worker started from a short-lived thread (a web server's executor) is not killed when that thread
    ends: PR_SET_PDEATHSIG follows the thread that forks, and the study forks from its own."""
    study = _open(raw, tmp_path, opened)
    p = study.join(simulated=False)
    thread = threading.Thread(target=_to_teaching, args=(study, p.code))
    thread.start()
    thread.join()
    _until(study, lambda: study.teaching_endpoint(p.code) is not None)
    time.sleep(0.5)
    study.poll()
    assert study.overview()[0]["worker"] == "ready"
    assert [e["event"] for e in layout.read_events(study.directory)].count("worker_exit") == 0


def test_nothing_starts_after_close(raw: dict[str, Any], tmp_path: Path, opened: list[Study]) -> None:
    study = _open(raw, tmp_path, opened)
    p = study.join(simulated=False)
    study.advance(p.code, "consent", "agree", {})
    study.advance(p.code, "instructions", "next", {})
    study.advance(p.code, "practice", "next", {})
    study.close()
    assert study.advance(p.code, "calibration", "skip", {})["step"] == "teaching"  # kept for the next open
    study.poll()
    assert study.overview()[0]["worker"] == "none"
