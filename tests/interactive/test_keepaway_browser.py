"""The keepaway browser trainer: presses on the simulated clock, credit into H^, pacing, frames, config."""

from __future__ import annotations

import json
import re
import threading

import pytest
import torch
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig
from hfrl_torch.envs.keepaway.records import KeepawayRecords
from hfrl_torch.envs.keepaway.simulator import KeepawaySimulator
from hfrl_torch.experiment import factories
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.experiment.config import validate_train
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.interactive.keepaway_live import BrowserKeeperTrainer, KeepawayWatcher
from hfrl_torch.interactive.live import DEFAULT_SPEED, LiveTeaching
from hfrl_torch.interactive.messages import Feedback, Finish, Presence
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.models.tile_coding import TileCoding
from hfrl_torch.trainers.queue_trainer import QueueTrainer

CONFIG = KeepawayConfig(decision_period_cycles=5, **TASKS["exact"])


def _fake_clock(start: float = 100.0) -> tuple[list[float], list[float], TeachingSession]:
    clock, slept = [start], []

    def sleep(s: float) -> None:
        slept.append(s)
        clock[0] += s

    return clock, slept, TeachingSession(actions_per_s=2.0, clock=lambda: clock[0], sleep=sleep)


def _press(session: TeachingSession, wall: float, value: float) -> None:
    session.queue.put(FeedbackEvent(time=wall, value=value, source="human:browser"))


def test_presses_are_placed_on_the_fields_simulated_clock_and_logged(tmp_path):
    _, _, session = _fake_clock()
    log = FeedbackLog(tmp_path / "feedback.jsonl", session="run1")
    trainer = BrowserKeeperTrainer(session, fields=2, log=log)
    now = torch.tensor([5.6, 9.0], dtype=torch.float64)
    _press(session, 99.0, 1.0)  # before anything was shown: credited now
    values, times = trainer.poll(now)
    assert values.tolist() == [1.0, 0.0] and times.tolist() == [5.6, 0.0]
    for i in range(4):  # frames at real time: 10 per second
        trainer.timeline.shown(100.0 + i / 10, 5.0 + i / 10, episode=3, step=6 + i // 2)
    _press(session, 100.45, 1.0)  # the frame on screen 0.3 s before showed 5.1 s: credited at 5.4 s
    _press(session, 100.65, -1.0)  # 0.3 s before: 5.3 s; 5.6 s is past the field's clock: credited at it
    now = torch.tensor([5.5, 9.0], dtype=torch.float64)
    assert trainer.poll(now)[1].tolist() == pytest.approx([5.4, 0.0])  # one press per poll...
    values, times = trainer.poll(now)
    assert values.tolist() == [-1.0, 0.0] and times.tolist() == pytest.approx([5.5, 0.0])  # ...in order
    assert trainer.poll(now)[0].tolist() == [0.0, 0.0]
    assert trainer.give(torch.zeros(2, 13), torch.zeros(2), torch.ones(2), torch.zeros(2))[0].eq(0).all()
    log.close()
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert [e.time for e in events] == pytest.approx([5.6, 5.4, 5.5])
    assert [(e.value, e.episode, e.step) for e in events] == [(1.0, -1, -1), (1.0, 3, 6), (-1.0, 3, 7)]
    assert {(e.source, e.session) for e in events} == {("human:browser", "run1/browser")}
    assert trainer.state_dict() == {"given": 3, "positive": 2, "waiting": [], "now": 5.5}


def test_a_logged_press_waiting_for_its_poll_is_in_the_checkpoint(tmp_path):
    _, _, session = _fake_clock()
    log = FeedbackLog(tmp_path / "feedback.jsonl", session="run1")
    trainer = BrowserKeeperTrainer(session, fields=1, log=log)
    _press(session, 100.7, 1.0)
    _press(session, 100.8, -1.0)
    now = torch.tensor([5.5], dtype=torch.float64)
    assert trainer.poll(now)[0].tolist() == [1.0]  # the second press, logged, waits for the next poll...
    again = BrowserKeeperTrainer(session)
    again.load_state_dict(trainer.state_dict())  # ...and a resumed run gives it (the log holds it already)
    assert again.given == 2 and [(e.value, e.seq) for e in again.waiting] == [(-1.0, 1)]
    assert again.poll(now)[0].tolist() == [-1.0]
    log.close()


def test_presses_left_in_the_queue_at_stop_are_logged_on_the_fields_clock(tmp_path):
    _, _, session = _fake_clock()
    log = FeedbackLog(tmp_path / "feedback.jsonl", session="run1")
    trainer = BrowserKeeperTrainer(session, fields=1, log=log)
    assert session.log_left == trainer.log_left
    trainer.timeline.shown(100.0, 5.0, episode=2, step=4)
    trainer.poll(torch.tensor([5.2], dtype=torch.float64))
    _press(session, 100.4, 1.0)  # acknowledged, then the run stops before the next poll
    _press(session, 100.5, -1.0)
    teaching = LiveTeaching(TeachingServer(session, port=0), session, QueueTrainer(session.queue, log=log))
    assert teaching.stop() == 2  # the server never started: stop only drains
    log.close()
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert [(e.value, e.time, e.episode, e.step) for e in events] == [(1.0, 5.2, 2, 4), (-1.0, 5.2, 2, 4)]


def test_a_press_credits_the_decisions_in_its_window_in_h_hat():
    _, _, session = _fake_clock()
    trainer = BrowserKeeperTrainer(session)
    model = TileCoding([1.0, 1.0], num_actions=3, learners=1, tilings=4, size=2**12)
    tamer, channel = KeeperTamer(model, 1, alpha=1.0), FeedbackChannel(1)
    tiles = [model.tiles(torch.tensor([[x, x]]))[:, 0] for x in (0.0, 5.0, 10.0)]  # disjoint tiles
    for t, tile in zip((3.0, 4.5, 5.2), tiles, strict=True):
        tamer.record(torch.tensor([True]), torch.tensor([0]), tile, torch.tensor([t]))
    trainer.timeline.shown(200.0, 5.1, 0, 2)
    _press(session, 200.3, 1.0)  # credited at 5.1 + 0.3 = 5.4 s: the 500 ms window reaches back to 4.9 s
    now = torch.tensor([5.6], dtype=torch.float64)
    channel.put(*trainer.poll(now), trainer.source)
    assert tamer.learn(channel.deliver(now)) == 2
    h = [model(torch.tensor([0]), tile).item() for tile in tiles]
    assert h[0] == 0.0 and h[1] > 0 and h[2] > 0  # the decision of 3.0 s ended at 4.5 s: no credit


def test_watcher_paces_while_taught_and_runs_free_when_nobody_watches():
    clock, slept, session = _fake_clock()
    sim = KeepawaySimulator(1, CONFIG, seed=0)
    trainer = BrowserKeeperTrainer(session)
    watcher = KeepawayWatcher(trainer, KeepawayRecords(1, 3), CONFIG)
    watcher.attach(sim)
    sim.step()  # nobody has the page open: no frame, no wait
    assert watcher.frames == 0 and not slept
    session.connect()
    for _ in range(10):
        sim.step()
    assert watcher.frames == 10 and slept == pytest.approx([0.1] * 9)  # real time at speed 2: 10 cycles/s
    assert [s.sim for s in trainer.timeline] == pytest.approx([0.2 + i / 10 for i in range(10)])
    session.apply(Presence(here=False))  # "I'm away": full speed, a frame now and then
    for _ in range(20):
        sim.step()
    assert len(slept) == 9 and watcher.frames == 10  # the fake clock stands still: no frame due yet
    clock[0] += 0.25
    sim.step()
    assert watcher.frames == 11 and session.latest()[1]["phase"] == "away"
    session.apply(Presence(here=True))
    session.paused = True
    stepper = threading.Thread(target=sim.step)
    stepper.start()
    stepper.join(timeout=0.3)
    assert stepper.is_alive()  # paused while the person watches
    session.disconnect()  # the page closes: the pause ends with it
    stepper.join(timeout=5)
    assert not stepper.is_alive()


def test_frame_has_what_the_page_draws_and_the_curve_gets_hold_times():
    _, _, session = _fake_clock()
    session.connect()
    records = KeepawayRecords(1, 3)
    trainer = BrowserKeeperTrainer(session)
    sim = KeepawaySimulator(1, CONFIG, seed=1)
    watcher = KeepawayWatcher(trainer, records, CONFIG, lambda: 0.75, curve_every=2)
    watcher.attach(sim)
    for _ in range(3):
        sim.step(torch.tensor([1]))
    frame = json.loads(json.dumps(session.latest()[1]))
    assert frame["type"] == "keepaway" and frame["region"] == [20.0, 20.0]
    assert len(frame["keepers"]) == 3 and len(frame["takers"]) == 2 and len(frame["ball"]) == 2
    assert -1 <= frame["holder"] < 3 and -1 <= frame["target"] < 3
    assert frame["time_s"] == pytest.approx(0.3) and frame["episode"] == 1 and frame["weight"] == 0.75
    assert frame["real_time"] == 2.0 and isinstance(frame["action"], str) and frame["phase"] == "watch"
    for seconds in (6.0, 8.0):
        ended = {keys.DONE: torch.tensor([[True]]), keys.EPISODE_CYCLES: torch.tensor([int(seconds * 10)])}
        watcher(TensorDict({"next": ended}, batch_size=[1]))
    assert session.latest_curve()[1]["curve"] == [[1.0, 7.0, 1.0]]  # every cycle of the block was taught
    sim.step()
    assert json.loads(json.dumps(session.latest()[1]))["mean_hold_s"] == 7.0


def test_the_page_says_which_decisions_the_teaching_changed_and_counts_them_per_episode():
    _, _, session = _fake_clock()
    session.connect()
    records = KeepawayRecords(1, 3)
    sim = KeepawaySimulator(1, CONFIG, seed=1)
    watcher = KeepawayWatcher(BrowserKeeperTrainer(session), records, CONFIG)
    watcher.attach(sim)

    def decide(alone: int) -> dict:
        decided = watcher.steered[1]
        watcher.deciding(alone)
        while watcher.steered[1] == decided:
            sim.step(torch.tensor([1]))
        return json.loads(json.dumps(session.latest()[1]))

    frame = decide(0)  # Q alone would have held the ball
    assert re.fullmatch(r"keeper [123] would have held the ball", frame["without_you"]) and frame[
        "steered"
    ] == [1, 1]
    frame = decide(-1)  # the teaching did not change this one
    assert frame["without_you"] is None and frame["steered"] == [1, 2]
    assert decide(2)["without_you"].endswith(" would have passed to its second-nearest teammate")
    ended = {keys.DONE: torch.tensor([[True]]), keys.EPISODE_CYCLES: torch.tensor([80])}
    watcher(TensorDict({"next": ended}, batch_size=[1]))
    assert watcher.frame(sim.state)["steered"] is None  # counted per episode
    assert watcher.frame(sim.state)["without_you"] is None


def test_a_taught_loop_learns_from_presses_at_real_time(tmp_path, monkeypatch, run_learner):
    clock, _, session = _fake_clock(0.0)
    presses = [(3.0, 1.0), (6.0, -1.0), (9.0, 1.0)]

    def sleep(s: float) -> None:  # the person presses while the keepers play
        clock[0] += s
        while presses and presses[0][0] <= clock[0]:
            session.apply(Feedback(presses.pop(0)[1]))

    session.sleep = sleep
    session.connect()
    monkeypatch.setattr(  # not served
        factories,
        "make_live_teaching",
        lambda cfg, view, fusion, drain, *page: LiveTeaching(
            TeachingServer(session, port=0), session, drain(session)
        ),
    )
    over = ["domain=keepaway", "trainer=interactive", "trainer.wait_for_page_s=0", "agent.table_bits=12"]
    told: list[int] = []
    deciding = KeepawayWatcher.deciding
    monkeypatch.setattr(
        KeepawayWatcher, "deciding", lambda self, alone: told.append(alone) or deciding(self, alone)
    )
    learner, _ = run_learner(tmp_path, *over, f"agent.hours={150 / 36000}", "fusion.weight=0.5")
    assert told and set(told) <= {-1, 0, 1, 2}  # each decision of the watched field, with Q's move or -1
    assert 14.85 <= clock[0] <= 17.0  # 150+ cycles at real time: the last step may run a few more
    assert not presses and learner.feedback.tolist() == [3] and learner.tamer.model.weight.abs().sum() > 0
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert [e.value for e in events] == [1.0, -1.0, 1.0] and {e.source for e in events} == {"human:browser"}
    assert [e.time for e in events] == pytest.approx([3.1, 6.1, 9.1], abs=0.11)  # wall = sim, one frame late


def _cfg(*overrides: str):
    return compose_config("train", "domain=keepaway", *overrides)


def test_config_of_the_keepaway_browser_trainer():
    cfg = _cfg("trainer=interactive")
    validate_train(cfg)
    assert cfg.agent.learners == 1  # one person teaches one team: the config's own default
    assert (
        _cfg("trainer=interactive", "agent.learners=4").agent.learners == 4
    )  # a value given wins (and fails)
    assert (
        cfg.fusion.name == "linear" and cfg.trainer.actions_per_s is None and DEFAULT_SPEED["keepaway"] == 2.0
    )
    assert cfg.domain.decision_period_cycles == 5
    validate_train(_cfg("trainer=interactive", "fusion=human_only"))
    for overrides, message in [
        (["agent.learners=4"], "agent.learners=4 with trainer=interactive: one person teaches one team"),
        (["trainer.port=70000"], "trainer.port=70000 is invalid"),
        (["trainer.actions_per_s=0.1"], "trainer.actions_per_s=0.1 is invalid"),
        (["agent.fields_per_learner=2"], "one trainer watches one field"),
    ]:
        with pytest.raises(ConfigError, match=message) as info:
            validate_train(_cfg("trainer=interactive", *overrides))
        assert "\n" not in str(info.value)


def test_finish_from_the_page_ends_the_keepers_run_with_a_checkpoint(tmp_path, monkeypatch, run_learner):
    clock, _, session = _fake_clock(0.0)
    ended = []

    def sleep(s: float) -> None:  # the person presses once, then asks to finish and save
        clock[0] += s
        if clock[0] >= 2.0 and session.taken == 0:
            session.apply(Feedback(1.0))
        if clock[0] >= 4.0 and session.ending is None:
            session.apply(Finish())

    session.sleep = sleep
    session.connect()

    def live(cfg, view, fusion, drain, *page):
        page = LiveTeaching(TeachingServer(session, port=0), session, drain(session))
        monkeypatch.setattr(page, "stop", lambda reason, saved: ended.append((reason, saved)) or 0)
        return page

    monkeypatch.setattr(factories, "make_live_teaching", live)
    over = ["domain=keepaway", "trainer=interactive", "trainer.wait_for_page_s=0", "agent.table_bits=12"]
    learner, final = run_learner(tmp_path, *over, "agent.hours=0.05", "agent.log_minutes=0.05")
    assert 4.0 <= clock[0] < 4.5  # the chunk ended at the request, not at the 3 simulated minutes
    assert final is not None and not learner.done and learner.stop_requested
    [(reason, saved)] = ended
    assert reason == "finished_by_you" and saved["checkpoint"] == str(tmp_path / "checkpoints" / "last.pt")
    assert saved["resume"] == f"python train.py resume={tmp_path}"  # not finished: no budget to add
    assert int(load_checkpoint(tmp_path)["state"]["human"]["feedback"].sum()) == 1
