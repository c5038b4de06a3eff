"""kill -9 of a whole study mid-study (the server and every participant's train.py at once), then the same
command again: every participant is back at their step (one at the instructions, two teaching), the
teaching participants' workers come back with ``resume=``, and every press acknowledged through the
study's proxy before the kill is in that participant's feedback log exactly once (a flood of presses, one
participant paused: the loop of a paused run drains nothing, so its presses are on disk only in the press
journal when the kill comes)."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import aiohttp
from study_proc import TETRIS, StudyProc, study_args

from hfrl_torch.feedback.log import read_feedback_log
from hfrl_torch.interactive.journal import JOURNAL_NAME, read_journal
from hfrl_torch.study import layout
from hfrl_torch.study.client import Participant, check_presses

FLOOD_GAP_S = (0.12, 0.25)  # 4-8 presses a second, under the run's 20 messages a second
ACKED_BEFORE_KILL = 12


async def _flood_then_kill(study: StudyProc, directory: Path) -> tuple[list[Participant], str]:
    """A third participant stops reading at the instructions; two flood their runs with presses (the
    second pauses its run after 4); once each has ``ACKED_BEFORE_KILL`` presses acknowledged (the second's
    mostly while paused), the study is killed. Returns the two teachers and the reader's code."""
    reader = Participant(study.base, 3)
    async with aiohttp.ClientSession() as client:
        reader.record.code = await reader._join(client)
        assert (await reader._step(client, "consent", "agree"))["step"] == "instructions"
    people = [
        Participant(study.base, seed, presses=None, gap_s=FLOOD_GAP_S, pause_after=pause, finish=False)
        for seed, pause in ((1, None), (2, 4))
    ]
    async with aiohttp.ClientSession() as client:
        tasks = [asyncio.ensure_future(p.run(client)) for p in people]
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            acked = [len(p.teacher.record.acked) if p.teacher else 0 for p in people]
            if min(acked) >= ACKED_BEFORE_KILL:
                break
            if any(t.done() for t in tasks):
                raise AssertionError(f"a participant stopped: {[p.record for p in people]}")
            await asyncio.sleep(0.05)
        else:
            teachers = [p.teacher for p in people if p.teacher is not None]
            said = [
                (
                    [x.error for x in t.record.presses if x.error][-3:],
                    t.record.errors,
                    t.record.connections,
                    t.settings,
                )
                for t in teachers
            ]
            raise AssertionError(
                f"presses acknowledged before the kill: {acked}; the pages' last refusals, errors, "
                f"connections and settings: {said}; the study's log:\n{study.log.read_text()}"
            )
        study.kill([layout.worker_pid(directory, p.record.code) for p in people])  # presses in flight
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    return people, reader.record.code


async def _ready(base: str, codes: list[str], timeout: float = 90) -> list[dict]:
    """Each participant's state once their teaching run accepts the page again."""
    async with aiohttp.ClientSession() as client:
        deadline = time.monotonic() + timeout
        while True:
            states = []
            for code in codes:
                async with client.get(f"{base}/p/{code}/api/state") as r:
                    states.append(await r.json())
            over = any(s["step"] != "teaching" for s in states) or time.monotonic() > deadline
            if over or all(s["teaching"]["ready"] for s in states):
                return states
            await asyncio.sleep(0.5)


def _journal_and_log(directory: Path, code: str) -> str:
    """The run's journaled presses against its log's browser events and the worker's log's end, for a
    failure's message."""
    run = layout.run_dir(directory, code)
    journal = read_journal(run / JOURNAL_NAME)
    events = [e for e in read_feedback_log(run / "feedback.jsonl").events if e.session.endswith("/browser")]
    worker = layout.worker_log(directory, code)
    journaled = [(j.n, j.value, j.source, j.episode, j.step) for j in journal]
    logged = [(e.seq, e.value, e.source, e.episode, e.step) for e in events]
    tail = worker.read_text()[-3000:] if worker.exists() else ""
    return f"journal (n, value, source, episode, step): {journaled}\nlog (seq, ...): {logged}\n{tail}"


def test_kill_9_of_the_study_loses_no_acknowledged_press_and_resumes_everyone(tmp_path):
    directory = tmp_path / "study"
    args = study_args(directory, 3, {"tetris": TETRIS})
    study = StudyProc(args, tmp_path / "first.log")
    try:
        people, reading = asyncio.run(_flood_then_kill(study, directory))
    finally:
        study.kill()
    codes = [p.record.code for p in people]
    paused = people[1].teacher
    assert paused is not None and paused.paused_ack.is_set()
    assert sum(bool(p.ack and p.ack["paused"]) for p in paused.record.presses) >= ACKED_BEFORE_KILL - 4
    assert not any("Interrupted" in layout.worker_log(directory, c).read_text() for c in codes)  # killed
    before = {c: json.loads(layout.participant_json(directory, c).read_text())["step"] for c in codes}
    assert before == {c: "teaching" for c in codes}

    again = StudyProc(args, tmp_path / "again.log")  # the same command, the same directory
    try:
        states = asyncio.run(_ready(again.base, codes))
        assert [s["step"] for s in states] == ["teaching", "teaching"]
        assert json.loads(layout.participant_json(directory, reading).read_text())["step"] == "instructions"
        assert all(s["teaching"]["ready"] for s in states), again.log.read_text()[-3000:]
        starts = [e for e in layout.read_events(directory) if e["event"] == "worker_start"]
        assert sorted(e["code"] for e in starts if e["resume"]) == sorted(codes)
        for person in people:
            assert person.teacher is not None
            check = check_presses(
                layout.run_dir(directory, person.record.code), person.teacher.record.presses
            )
            assert check["acked"] >= ACKED_BEFORE_KILL
            seen = (
                _journal_and_log(directory, person.record.code)
                if check["lost"] or check["duplicated"]
                else ""
            )
            assert check["lost"] == 0 and check["duplicated"] == 0, (check, seen)
            assert check["logged"] == check["journaled"] >= check["acked"], (check, seen)
    finally:
        again.stop()
