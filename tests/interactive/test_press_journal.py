"""The press journal: a press the page is told was taken is on disk first, and a run that starts again logs
the journal's presses its feedback log lacks, each exactly once."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log, read_feedback_log
from hfrl_torch.interactive.journal import (
    JOURNAL_NAME,
    PressJournal,
    PressJournalError,
    browser_session,
    read_journal,
)
from hfrl_torch.interactive.keepaway_live import BrowserKeeperTrainer
from hfrl_torch.interactive.messages import Feedback, Pause
from hfrl_torch.interactive.session import PAUSED_SOURCE, NotTaken, TeachingSession
from hfrl_torch.interactive.tetris_live import BrowserTetrisTrainer


class Clock:
    def __init__(self, t: float = 100.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def _teaching(tmp_path, keepaway: bool):
    """A session whose presses go through a browser trainer into a feedback log, journaled as in train.py."""
    clock = Clock()
    session = TeachingSession(clock=clock)
    log = FeedbackLog(tmp_path / "feedback.jsonl", session="run")
    trainer = BrowserKeeperTrainer(session, 1, log) if keepaway else BrowserTetrisTrainer(session, log)
    session.journal = PressJournal(tmp_path / JOURNAL_NAME, log, session.reaction_s, trainer.discrete)
    return session, log, trainer, clock


def _show(session: TeachingSession, clock: Clock, sim: float, episode: int, step: int) -> None:
    session.publish({"type": "frame"})
    session.shown(sim, episode, step, f"step {step}")
    clock.t += 0.5


def test_each_press_taken_is_in_the_journal_before_it_is_acknowledged(tmp_path):
    session, log, _, clock = _teaching(tmp_path, keepaway=True)
    _show(session, clock, 5.0, 2, 7)
    replies = [session.apply(Feedback(value=v, id=i)) for i, v in enumerate([1.0, -1.0, 1.0])]
    entries = read_journal(tmp_path / JOURNAL_NAME)
    assert [r["given"] for r in replies] == [1, 2, 3]
    assert [(e.n, e.value, e.episode, e.step, e.sim) for e in entries] == [
        (0, 1.0, 2, 7, 5.0),
        (1, -1.0, 2, 7, 5.0),
        (2, 1.0, 2, 7, 5.0),
    ]
    log.close()


@pytest.mark.parametrize("keepaway", [True, False])
def test_presses_acknowledged_while_paused_and_never_drained_are_logged_once_when_the_run_starts_again(
    tmp_path, keepaway
):
    session, _, trainer, clock = _teaching(tmp_path, keepaway)
    _show(session, clock, 5.0, 0, 3)
    session.apply(Feedback(value=1.0, id=0))
    if keepaway:
        trainer.poll(torch.tensor([5.5]))  # the loop drained and logged the first press
    else:
        trainer.late(clock())
    session.apply(Pause(paused=True))
    acked = [session.apply(Feedback(value=-1.0 if i % 3 else 1.0, id=i + 1)) for i in range(20)]
    assert len(acked) == 20 and len(load_feedback_log(tmp_path / "feedback.jsonl")) == 1
    # kill -9: nothing more runs; the journal and the log stay as they are on disk
    log2 = FeedbackLog(tmp_path / "feedback.jsonl", session="run")
    journal = PressJournal(tmp_path / JOURNAL_NAME, log2, session.reaction_s, trainer.discrete)
    assert len(journal.recovered) == 20
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert [e.seq for e in events] == list(range(21))
    assert {e.session for e in events} == {browser_session("run")}
    assert [e.value for e in events[1:]] == [a["value"] for a in acked]
    assert all(e.source == PAUSED_SOURCE and (e.episode, e.step) == (0, 3) for e in events[1:])
    assert all(5.0 < e.time <= 5.0 + session.reaction_s + 1e-9 for e in events[1:])  # credited at the frame
    journal.close()
    again = PressJournal(tmp_path / JOURNAL_NAME, FeedbackLog(tmp_path / "feedback.jsonl", "run"), 0.3, True)
    assert again.recovered == [] and len(load_feedback_log(tmp_path / "feedback.jsonl")) == 21
    assert again.write(200.0, 1.0, "human:browser", None) == 21  # numbering goes on after both files


@pytest.mark.parametrize("keepaway", [True, False])
def test_two_equal_presses_one_logged_before_the_kill_and_one_recovered_after_are_both_read_back(
    tmp_path, keepaway
):
    """Two Good presses on one frame are equal in every field but their number. The loop logs the first; the
    second is journaled when the run is killed, and the restarted run's recovery logs it under a new header.
    A reader once dropped it as a resumed run's re-logged copy (one lost press in a study kill test)."""
    session, _, trainer, clock = _teaching(tmp_path, keepaway)
    _show(session, clock, 5.0, 0, 3)
    session.apply(Feedback(value=1.0, id=0))
    if keepaway:
        trainer.poll(torch.tensor([5.5]))
    else:
        trainer.late(clock())
    session.apply(Feedback(value=1.0, id=1))
    # kill -9, then the same run again
    journal = PressJournal(
        tmp_path / JOURNAL_NAME, FeedbackLog(tmp_path / "feedback.jsonl", "run"), 0.3, trainer.discrete
    )
    assert len(journal.recovered) == 1
    contents = read_feedback_log(tmp_path / "feedback.jsonl")
    first, second = contents.events
    assert (first.seq, second.seq) == (0, 1) and contents.duplicates == 0
    assert {k: v for k, v in first.to_dict().items() if k != "seq"} == {
        k: v for k, v in second.to_dict().items() if k != "seq"
    }  # equal but for their numbers: what the reader must not take for a copy
    journal.close()


def test_a_press_the_journal_cannot_write_is_refused_and_not_counted(tmp_path):
    session, log, _, clock = _teaching(tmp_path, keepaway=True)
    _show(session, clock, 5.0, 0, 1)
    session.journal.close()
    with pytest.raises(NotTaken, match="could not be saved"):
        session.apply(Feedback(value=1.0, id=0))
    assert session.taken == 0 and len(session.queue) == 0 and session.not_taken == 1
    log.close()


def test_a_write_cut_short_is_dropped_and_a_corrupt_line_is_named(tmp_path):
    session, log, _, clock = _teaching(tmp_path, keepaway=True)
    _show(session, clock, 5.0, 0, 1)
    session.apply(Feedback(value=1.0, id=0))
    session.journal.close()
    path = tmp_path / JOURNAL_NAME
    with open(path, "ab") as f:
        f.write(b'{"n":1,"wall":1')  # a kill in the middle of a write
    journal = PressJournal(path, log, 0.3, False)
    assert len(journal.recovered) == 1 and path.read_bytes().count(b'"n":1,"wall":1') == 0
    journal.close()
    with open(path, "ab") as f:
        f.write(b'{"n": "x"}\n{"n":2}\n')
    with pytest.raises(PressJournalError, match=rf"{JOURNAL_NAME}:\d+ is corrupt"):
        PressJournal(path, log, 0.3, False)
    log.close()
