"""A trainer who leaves (``trainer.leave_after``): feedback stops there for good, in every taught loop, and
the effort that was given is counted."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.feedback.log import load_feedback_log
from hfrl_torch.trainers.departure import Departure


def test_present_by_episodes_and_by_minutes() -> None:
    episodes = torch.tensor([0, 4, 5, 9])
    assert Departure(5).present(episodes, 0.0).tolist() == [True, True, False, False]
    seconds = torch.tensor([0.0, 59.0, 60.0, 600.0])
    assert Departure(1, "minutes").present(episodes, seconds).tolist() == [True, True, False, False]
    assert Departure().present(episodes, seconds).all()
    assert Departure(0).present(episodes, seconds).sum() == 0  # a trainer who never came
    for d in (Departure(5), Departure(1, "minutes"), Departure(), Departure(0)):  # one learner: the same
        one = [d.present_one(int(e), float(t)) for e, t in zip(episodes, seconds, strict=True)]
        assert one == d.present(episodes, seconds).tolist(), d


def test_bad_departures_are_refused() -> None:
    with pytest.raises(ValueError, match="hours"):
        Departure(3, "hours")
    with pytest.raises(ValueError, match="leave_after"):
        Departure(-1)


def test_keepaway_trainer_leaves_after_its_episodes(tmp_path, run_learner) -> None:
    """No event is given on a field once its learner has finished ``leave_after`` episodes; the effort rows
    say so, and the weight goes on being chosen (the bandit) after the trainer has gone."""
    learner, final = run_learner(
        tmp_path,
        "domain=keepaway",
        "fusion=linear",
        "fusion.weight=adaptive",
        "agent.learners=2",
        "agent.hours=0",
        "agent.episodes=8",
        "agent.log_episodes=2",
        "trainer.leave_after=3",
    )
    effort = learner.effort
    gone = effort[:, 1] >= 3
    assert effort[~gone, 2].sum() > 0 and effort[gone, 2].sum() == 0
    assert effort[gone, 3].sum() == 0 and bool((effort[~gone, 3] > 0).all())
    assert final["feedback/trainer_present_share"] == 0.0
    assert final["feedback/trainer_minutes_per_learner"] == pytest.approx(
        float(effort[:, 3].sum()) / 60.0 / 2
    )


def test_tetris_trainer_leaves_after_its_games(tmp_path, run_learner) -> None:
    learner, _ = run_learner(
        tmp_path,
        "agent=pg",
        "fusion=linear",
        "trainer=oracle",
        "agent.learners=2",
        "agent.games=5",
        "domain.width=6",
        "domain.height=6",
        "trainer.leave_after=2",
    )
    assert bool((learner.given[:, :2, 0].sum(1) > 0).all()) and learner.given[:, 2:].sum() == 0
    assert bool((learner.watched[:, :2] > 0).all()) and learner.watched[:, 2:].sum() == 0


def test_ce_trainer_leaves_after_its_iterations(tmp_path, run_learner) -> None:
    learner, _ = run_learner(
        tmp_path,
        "agent=cem",
        "fusion=linear",
        "fusion.weight=adaptive",
        "trainer=oracle",
        "agent.iterations=3",
        "agent.population=10",
        "agent.eval_games=2",
        "domain.width=6",
        "domain.height=6",
        "trainer.leave_after=1",
    )
    given = [r["feedback/given"] for r in learner.history]
    assert given[0] > 0 and given[1:] == [0.0, 0.0]
    assert [r["feedback/trainer_minutes"] > 0 for r in learner.history] == [True, False, False]


CARTPOLE = ("domain=gym", "domain.env_id=CartPole-v1", "trainer.reference=examples.cartpole:reference")
GYM_PPO = (*CARTPOLE, "agent=ppo", "agent.boards=4", "agent.steps_per_batch=32", "agent.minibatch_size=128")
GYM_DQN = (
    *CARTPOLE,
    "agent=dqn",
    "agent.boards=4",
    "agent.steps_per_batch=8",
    "agent.learn_after=64",
    "agent.epsilon_frames=400",
    "agent.eval_episodes=2",
    "agent.frames=480",
    "agent.eval_every=160",
)
KEEPAWAY_DQN = (
    "domain=keepaway",
    "agent=dqn",
    "trainer=oracle",
    "human=mlp",
    "human.cells=[16]",
    "domain.decision_period_cycles=5",
    "agent.boards=4",
    "agent.frames=240",
    "agent.eval_every=80",
    "agent.eval_episodes=2",
    "agent.learn_after=32",
    "agent.batch_size=16",
    "agent.cells=[16]",
)


@pytest.mark.parametrize(
    ("task", "leave"),
    [
        ((*GYM_DQN, "fusion=linear"), ("trainer.leave_after=0.1", "trainer.leave_unit=minutes")),  # 30 steps
        ((*GYM_PPO, "fusion=linear", "agent.frames=640", "agent.eval_every=128"), ("trainer.leave_after=6",)),
        ((*KEEPAWAY_DQN, "fusion=reward_shaping", "fusion.weight=0.5"), ("trainer.leave_after=3",)),
    ],
    ids=["gym-dqn-minutes", "gym-ppo-episodes", "keepaway-dqn-episodes"],
)
def test_collector_learners_trainer_leaves_and_what_it_gave_before_is_the_same(
    tmp_path, run_learner, one_thread, task, leave
) -> None:
    """DQN and PPO on the collector path: the trainer who leaves gives, up to the moment it leaves, the very
    events of a trainer who stays (the same seed), and none after; the points say it is gone."""
    _, stayed = run_learner(tmp_path / "stays", *task)
    learner, left = run_learner(tmp_path / "leaves", *task, *leave)
    events = [
        (e.time, e.value, e.episode, e.step)
        for e in load_feedback_log(tmp_path / "leaves" / "feedback.jsonl")
    ]
    every = [
        (e.time, e.value, e.episode, e.step) for e in load_feedback_log(tmp_path / "stays" / "feedback.jsonl")
    ]
    assert 0 < len(events) < len(every) and events == every[: len(events)]
    assert learner.history[-1]["trainer/present"] == 0.0 and learner.history[0]["trainer/present"] == 1.0
    assert left["feedback_events"] == len(events) < stayed["feedback_events"]
    assert 0 < left["trainer_minutes"] < stayed["trainer_minutes"]  # its time is booked while it watched
