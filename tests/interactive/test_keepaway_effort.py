"""The human effort of a keepaway run taught in the browser: the presses the keepers learn from are booked
per episode, as the simulated oracle's events are, and reach ``evaluate.py``'s effort table."""

from __future__ import annotations

import torch
from omegaconf import OmegaConf

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.experiment import factories
from hfrl_torch.experiment.aggregate import find_runs
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.interactive.live import LiveTeaching
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession


def test_presses_drained_from_the_page_are_booked_as_effort(tmp_path, monkeypatch, run_learner):
    clock = [0.0]
    session = TeachingSession(actions_per_s=2.0, clock=lambda: clock[0])
    pressed: list[float] = []

    def sleep(s: float) -> None:  # the person presses about once a second of wall time, + and - in turn
        clock[0] += s
        if clock[0] >= len(pressed) + 1.0:
            value = 1.0 if len(pressed) % 2 == 0 else -1.0
            pressed.append(value)
            session.queue.put(FeedbackEvent(time=clock[0], value=value, source="human:browser"))

    session.sleep = sleep
    session.connect()
    monkeypatch.setattr(  # not served: the presses go straight onto the session's queue
        factories,
        "make_live_teaching",
        lambda cfg, view, fusion, drain, *_: LiveTeaching(
            TeachingServer(session, port=0), session, drain(session)
        ),
    )
    over = ["domain=keepaway", "trainer=interactive", "trainer.wait_for_page_s=0", "agent.table_bits=12"]
    learner, final = run_learner(
        tmp_path, *over, "agent.hours=0", "agent.episodes=4", "agent.log_episodes=2", "fusion.weight=0.5"
    )
    assert final is not None and learner.done
    learned = int(learner.feedback.sum())
    logged = load_feedback_log(tmp_path / "feedback.jsonl")
    assert learned >= 5 and learned == learner.trainer.given and len(logged) == len(pressed)
    effort = load_checkpoint(tmp_path)["state"]["human"]["effort"]
    assert effort.shape[0] == 4 and int(effort[:, 2].sum()) == learned  # one row per episode, every press
    assert float(final["feedback/events_per_learner"]) == learned
    OmegaConf.save(learner.cfg, tmp_path / "config.yaml")  # (train.py writes it; run_learner does not)
    runs, _ = find_runs([tmp_path])
    [run] = runs
    assert [r["feedback_events"] for r in run.rows] == torch.cat(
        [effort[:2, 2].sum().view(1), effort[:, 2].sum().view(1)]
    ).tolist()


def test_a_replayed_log_is_booked_as_effort_too(tmp_path, run_learner):
    recorded = FeedbackLog(tmp_path / "recorded.jsonl", session="person/browser", fsync=False)
    recorded.extend(
        FeedbackEvent(time=0.5 + i, value=1.0 if i % 2 else -1.0, source="human:browser") for i in range(12)
    )
    recorded.close()
    over = ["domain=keepaway", "trainer=replay", f"trainer.log={tmp_path / 'recorded.jsonl'}"]
    run = tmp_path / "run"
    learner, final = run_learner(
        run, *over, "agent.learners=1", "agent.table_bits=12", "agent.hours=0", "agent.episodes=4"
    )
    assert final is not None and learner.done
    learned = int(learner.feedback.sum())
    effort = load_checkpoint(run)["state"]["human"]["effort"]
    assert learned >= 5 and effort.shape[0] == 4 and int(effort[:, 2].sum()) == learned
