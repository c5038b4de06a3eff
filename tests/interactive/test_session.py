"""The session the page and the loop share: a press is filed under what was on screen the reaction
allowance before it, taken only when someone can judge, told back exactly; stopping ends pacing at once."""

from __future__ import annotations

import threading
import time

import pytest

from hfrl_torch.feedback.events import FeedbackQueueClosedError
from hfrl_torch.fusion import AnnealedWeight, ConstantWeight, Fusion, TrustWeight
from hfrl_torch.fusion.bandit import BanditWeight
from hfrl_torch.fusion.paired import PairedWeight
from hfrl_torch.fusion.schedules import SearchedWeight
from hfrl_torch.interactive.explain import weight_sentence
from hfrl_torch.interactive.messages import Feedback, Finish, Pause, Presence, Speed
from hfrl_torch.interactive.session import PAUSED_SOURCE, SOURCE, NotTaken, TeachingSession
from hfrl_torch.interactive.timeline import ScreenTimeline, Shown, credit_time


def _session(start: float = 100.0) -> tuple[list[float], TeachingSession]:
    clock = [start]
    return clock, TeachingSession(actions_per_s=2.0, clock=lambda: clock[0], sleep=lambda s: None)


def _show(session: TeachingSession, clock: list[float], wall: float, step: int, label: str) -> None:
    clock[0] = wall
    session.shown(sim=wall - 0.01, episode=4, step=step, label=label)


def test_a_press_is_filed_under_the_frame_on_screen_the_reaction_allowance_before_it():
    clock, session = _session()
    for k, wall in enumerate((100.0, 100.5, 101.0)):
        _show(session, clock, wall, k, f"placement {k + 1}")
    clock[0] = 101.2  # 0.3 s before: 100.9, placement 2 was on screen (placement 3 came at 101.0)
    reply = session.apply(Feedback(1.0, id=7))
    assert reply == {
        "id": 7,
        "given": 1,
        "paused": False,
        "value": 1.0,
        "filed": "placement 2",
        "episode": 4,
        "step": 1,
    }
    clock[0] = 101.31  # 0.3 s before: 101.01, placement 3
    assert session.apply(Feedback(-1.0, id=8))["filed"] == "placement 3"
    events = session.queue.drain()
    assert [(e.time, e.value, e.step, e.episode, e.source) for e in events] == [
        (101.2, 1.0, 1, 4, SOURCE),
        (101.31, -1.0, 2, 4, SOURCE),
    ]
    assert session.settings()["given"] == 2
    assert [p["filed"] for p in session.presses] == ["placement 2", "placement 3"]


def test_presses_are_refused_when_nobody_can_judge_and_the_page_is_told_why():
    clock, session = _session()
    session.set_live(False)  # as train.py starts it: nothing shown yet (start-up takes seconds)
    with pytest.raises(NotTaken, match="the run is starting: nothing is on screen to judge yet"):
        session.apply(Feedback(1.0))
    session.set_live(True)
    _show(session, clock, 100.0, -1, "")  # a frame with nothing to judge (a new game's empty board)
    clock[0] = 100.4
    with pytest.raises(NotTaken, match=r"no move had been made yet 0\.3 s before this press"):
        session.apply(Feedback(1.0))
    _show(session, clock, 100.5, 0, "T at column 4")
    clock[0] = 101.0
    session.apply(Presence(here=False))
    with pytest.raises(NotTaken, match="you said you are away"):
        session.apply(Feedback(1.0))
    session.apply(Presence(here=True))
    session.set_live(False)
    with pytest.raises(NotTaken, match="practising on its own"):
        session.apply(Feedback(1.0))
    session.set_live(True)
    session.apply(Pause(paused=True))  # paused: taken, filed under the frozen frame, marked
    reply = session.apply(Feedback(-1.0, id=3))
    assert reply["paused"] and reply["filed"] == "T at column 4"
    session.apply(Finish())
    assert session.ending == "finishing" and session.settings()["ending"] == "finishing"
    with pytest.raises(NotTaken, match="finishing and saving"):
        session.apply(Feedback(1.0))
    session.request_stop()
    with pytest.raises(NotTaken, match="the run is stopping"):
        session.apply(Feedback(1.0))
    assert [e.source for e in session.queue.drain()] == [PAUSED_SOURCE]
    assert (session.taken, session.taken_paused, session.not_taken) == (1, 1, 6)
    session.queue.close()
    session.ending = None
    with pytest.raises(FeedbackQueueClosedError):
        session.apply(Feedback(1.0))
    assert session.taken == 1  # nothing counted that the queue did not take


def test_a_session_that_shows_no_frames_takes_presses_unfiled():
    _, session = _session()
    assert session.apply(Feedback(1.0))["filed"] == "" and session.queue.drain()[0].step == -1


def test_settings_and_summary_say_what_the_page_shows():
    clock, session = _session()
    key = session.settings_key()
    session.apply(Speed(3.0))
    assert session.settings_key() != key
    session.set_progress(unit="rounds", done=2, total=5, left=3, left_s=12.0)
    session.add_point(1, 4.0, taught=1.0)
    session.add_point(2, 6.0)
    settings = session.settings()
    assert settings["actions_per_s"] == 3.0 and settings["progress"]["left"] == 3 and settings["live"]
    assert settings["curve"] == [[1.0, 4.0, 1.0], [2.0, 6.0, 0.0]]
    _show(session, clock, 100.0, 0, "O at column 1")
    clock[0] = 100.5
    session.apply(Feedback(1.0))
    end = session.summary("finished", {"run_dir": "/runs/x", "resume": "python train.py resume=/runs/x"})
    assert end["type"] == "end" and end["reason"] == "finished" and (end["given"], end["good"]) == (1, 1)
    assert end["presses"] == [
        {"value": 1.0, "filed": "O at column 1", "episode": 4, "step": 0, "paused": False}
    ]
    assert end["curve"] == settings["curve"] and end["resume"].endswith("resume=/runs/x")


def test_a_stop_ends_the_pacing_sleep_and_the_pause_at_once():
    session = TeachingSession(actions_per_s=0.5)  # the real clock and sleep: 2 s between actions
    session.connect()
    session.wait_turn()
    stopper = threading.Timer(0.2, session.request_stop)
    stopper.start()
    t0 = time.monotonic()
    session.wait_turn()
    assert time.monotonic() - t0 < 1.0  # cut short, not the 2 s period
    session.ending = None
    session.paused = True
    threading.Timer(0.2, session.request_stop).start()
    t0 = time.monotonic()
    session.wait_turn()  # paused while watched, until the stop
    assert 0.15 < time.monotonic() - t0 < 1.0


def test_a_dropped_page_is_waited_for_then_the_agent_goes_on_alone():
    session = TeachingSession(reconnect_s=0.5)
    assert not session.teaching()  # no page has opened yet: nothing to wait for
    session.connect()
    assert session.teaching()
    session.disconnect()
    threading.Timer(0.2, session.connect).start()  # it comes back within the wait
    t0 = time.monotonic()
    assert session.teaching()
    assert 0.15 < time.monotonic() - t0 < 0.45
    session.disconnect()  # it does not come back: the whole wait, then on alone, and no second wait
    t0 = time.monotonic()
    assert not session.teaching()
    assert 0.45 < time.monotonic() - t0 < 1.0
    t0 = time.monotonic()
    assert not session.page_open() and time.monotonic() - t0 < 0.05
    session.connect()
    session.disconnect()
    session.request_stop()  # a run that is stopping does not wait
    t0 = time.monotonic()
    assert not session.teaching() and time.monotonic() - t0 < 0.05
    with pytest.raises(ValueError, match=r"reconnect_s=-1 is invalid: must be at least 0 seconds"):
        TeachingSession(reconnect_s=-1)


def test_credit_time_and_the_timeline():
    timeline = ScreenTimeline(size=3)
    for k in range(4):
        timeline.shown(10.0 + k, 5.0 + k, episode=0, step=k)
    assert len(timeline) == 3 and timeline.at(9.0).step == 1  # the oldest kept
    seen = timeline.at(11.5)
    assert seen.step == 1 and timeline.after(seen).step == 2 and timeline.after(timeline.at(99)) is None
    later = Shown(12.0, 6.2, 0, 2)
    assert credit_time(seen, later, 0.3, now=9.0) == pytest.approx(6.3)  # min(S + r, now): the keepaway rule
    assert credit_time(seen, later, 0.3, now=9.0, discrete=True) == pytest.approx(
        6.2
    )  # not into the next step
    assert credit_time(seen, None, 0.0, now=9.0, discrete=True) > seen.sim  # strictly after its start
    assert credit_time(None, None, 0.3, now=9.0) == 9.0
    with pytest.raises(ValueError, match="size must be >= 1"):
        ScreenTimeline(0)


@pytest.mark.parametrize(
    ("scheme", "schedule", "said"),
    [
        ("linear", TrustWeight.from_initial(0.5), "trust factor (thesis eq. 4.4)"),
        ("linear", ConstantWeight(0.5), "fixed for this run (fusion.weight=0.5)"),
        ("annealed", AnnealedWeight(1.0, 0.98), "shrinks by a factor 0.98"),
        ("linear", SearchedWeight(1.0), "searched by the cross-entropy method"),
        ("reward_shaping", BanditWeight(1, [0.0, 0.1, 1.0]), "among 0, 0.1, 1 by a bandit"),
        ("linear", PairedWeight(1, [0.0, 0.25, 1.0]), "chosen among 0, 0.25, 1 (fusion.weight=adaptive)"),
        ("human_only", ConstantWeight(0.0), "alone (fusion=human_only)"),
    ],
)
def test_the_weight_is_explained_whatever_sets_it(scheme, schedule, said):
    fusion = Fusion.from_option(scheme, schedule)
    text = weight_sentence(scheme, fusion.describe_weight, "tetris")
    assert said in text and "\n" not in text
    if schedule.kind in ("trust", "search", "bandit", "paired"):
        assert "not you" in text  # never presented as a measure of the person
        assert "fixed" not in text  # CE's adaptive weight was once worded as fixed while it moved


def test_the_weight_sentence_speaks_of_the_domains_episodes():
    """Keepaway's page speaks of episodes and hold times, not games and lines."""
    fusion = Fusion.from_option("linear", TrustWeight.from_initial(0.5))
    text = weight_sentence("linear", fusion.describe_weight, "keepaway")
    assert "after every episode" in text and "how long the keepers kept the ball" in text
    assert "game" not in text and "lines" not in text
