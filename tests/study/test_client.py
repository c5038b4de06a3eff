"""The scripted participant's teaching side against a TeachingServer in this process (no train.py): its
presses are acknowledged and found in the journal and log exactly once, a frame gap over 1.5x the announced
period counts as late and no other does, and ``check_presses`` finds a lost and a duplicated press."""

from __future__ import annotations

import asyncio
import random
import threading
import time
from pathlib import Path

import pytest

from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.interactive.journal import PressJournal, browser_session
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.study.client import check_presses, percentile, run_ws

pytestmark = pytest.mark.serial  # frame gaps are timed
PERIOD_S = 0.2  # 5 placements a second
LATE_AT = 12  # the frame before this one is shown 3x the period long


def _play(session: TeachingSession, stop: threading.Event) -> None:
    """A Tetris game of placements at the session's pace, one of them held 3x as long, until ``stop``."""
    session.set_live(True)
    i = 0
    while not stop.is_set():
        session.publish({"type": "tetris", "phase": "watch", "game": 1, "placement": i + 1})
        session.shown(float(i), 0, i, f"placement {i + 1}")
        i += 1
        time.sleep(PERIOD_S * (3 if i == LATE_AT else 1))


@pytest.fixture
def run(tmp_path: Path):
    session = TeachingSession(actions_per_s=1 / PERIOD_S, reaction_s=0.1)
    log = FeedbackLog(tmp_path / "feedback.jsonl", "run")
    session.journal = PressJournal(tmp_path / "presses.jsonl", log, session.reaction_s, True)
    server = TeachingServer(session, port=0)
    server.start()
    stop = threading.Event()
    player = threading.Thread(target=_play, args=(session, stop), daemon=True)
    player.start()
    yield session, server, log
    stop.set()
    player.join()
    server.stop()


def test_presses_are_acknowledged_journaled_and_logged_once_and_one_late_frame_is_counted(run, tmp_path):
    session, server, log = run
    record = asyncio.run(run_ws(server.url, random.Random(3), presses=12, gap_s=(0.15, 0.3), finish=False))
    assert len(record.acked) == 12, [p.error for p in record.presses]
    assert record.connections == 1 and record.errors == []
    assert all(0 < p.ack_ms < 1000 for p in record.acked)
    assert percentile([p.ack_ms for p in record.acked], 50) is not None
    # the one frame held 3x is late; a loaded machine may oversleep another past 1.5x, never most of them
    assert record.steady_gaps >= 10 and 1 <= record.late_gaps <= 3, (record.steady_gaps, record.late_gaps)
    assert 2.5 < record.worst_gap_ratio < 6

    assert session.journal is not None
    session.journal.close()  # the loop drained nothing: a journal opened again logs every press
    PressJournal(tmp_path / "presses.jsonl", log, session.reaction_s, True).close()
    log.close()
    check = check_presses(tmp_path, record.presses)
    assert check == {
        "acked": 12,
        "journaled": 12,
        "logged": 12,
        "lost": 0,
        "duplicated": 0,
        "unacked_logged": 0,
    }

    lines = (tmp_path / "feedback.jsonl").read_text().splitlines(keepends=True)
    browser = [i for i, line in enumerate(lines) if browser_session("run") in line]
    doubled = [*lines[: browser[5] + 1], lines[browser[5]], *lines[browser[5] + 1 :]]
    (tmp_path / "feedback.jsonl").write_text("".join(doubled))
    assert check_presses(tmp_path, record.presses)["duplicated"] == 1
    (tmp_path / "feedback.jsonl").write_text("".join(lines[: browser[-1]]))  # the last press never logged
    assert check_presses(tmp_path, record.presses)["lost"] == 1
