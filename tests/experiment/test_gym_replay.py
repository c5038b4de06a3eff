"""``train.py domain=gym trainer=replay trainer.log=<feedback.jsonl>``: a gym run's feedback log given again
through the one replay (``trainers.replay.ReplayTrainer``, matched by board, episode and step) to DQN, PPO and
TAMER alone, and a log that cannot be read refused in one line before the run (issue 42)."""

from __future__ import annotations

import json

import pytest
import torch

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import load_feedback_log

CARTPOLE = ("domain=gym", "domain.env_id=CartPole-v1", "agent=dqn", "fusion=linear", "seed=3")
TINY = (
    "agent.boards=4",
    "agent.steps_per_batch=8",
    "agent.learn_after=64",
    "agent.frames_per_update=4",
    "agent.epsilon_frames=400",
    "agent.eval_episodes=2",
    "agent.frames=256",
    "agent.eval_every=128",
    "fusion.weight=1.0",  # H^ decides with Q: a replay that gave other events would play other episodes
    "human.replay_every=2",
    "trainer.reaction=0.2",
)
ORACLE = ("trainer=oracle", "trainer.reference=examples.cartpole:reference", "trainer.timing.enabled=false")


def _key(e: FeedbackEvent) -> tuple:
    return (e.session.split("/")[-1], e.episode, e.step, e.value, round(e.time, 6))


SMALL = ("agent.boards=4", "agent.frames=256", "agent.eval_every=128", "agent.eval_episodes=2")
LEARNERS = {
    "dqn": (*CARTPOLE, *TINY),
    "tamer": (
        "domain=gym",
        "domain.env_id=CartPole-v1",
        "seed=3",
        "agent=tamer",
        *SMALL,
        "human.replay_every=2",
    ),
    "ppo": (
        "domain=gym",
        "domain.env_id=CartPole-v1",
        "seed=3",
        "agent=ppo",
        "fusion=linear",
        "fusion.weight=1.0",
        *SMALL,
        "agent.steps_per_batch=8",
        "agent.minibatch_size=16",
        "human.replay_every=2",
    ),
}


@pytest.mark.parametrize("learner", list(LEARNERS))
def test_a_replayed_gym_run_receives_exactly_the_logged_events(run_learner, tmp_path, one_thread, learner):
    """DQN, TAMER alone and PPO fused take a replayed log alike: the same events on the same steps, so H^
    (and the policy) learn the same, point for point."""
    task = LEARNERS[learner]
    first, done = run_learner(tmp_path / "oracle", *task, *ORACLE, "trainer.frequency=0.5")
    log = tmp_path / "oracle" / "feedback.jsonl"
    recorded = load_feedback_log(log)
    assert len(recorded) > 50 and {e.source for e in recorded} == {"simulated:oracle"}
    assert {e.session.split("/")[-1] for e in recorded} == {f"board{b}" for b in range(4)}

    second, again = run_learner(tmp_path / "replay", *task, "trainer=replay", f"trainer.log={log}")
    replayed = load_feedback_log(tmp_path / "replay" / "feedback.jsonl")
    assert sorted(map(_key, replayed)) == sorted(map(_key, recorded))
    assert {e.source for e in replayed} == {"replay"}
    assert second.events == first.events > 0  # what H^ learned from, delivered on the same steps
    assert second.positive == first.positive
    for a, b in zip(first.human.model.parameters(), second.human.model.parameters(), strict=True):
        assert torch.equal(a, b)
    assert [r["eval/greedy_return_mean"] for r in second.history] == [
        r["eval/greedy_return_mean"] for r in first.history
    ]
    assert again["feedback_events"] == done["feedback_events"]


def _log_lines() -> list[str]:
    header = {"schema": "hfrl_torch.feedback", "version": 2, "session": "old", "created": 0.0}
    event = {"time": 0.2, "step": 0, "episode": 0, "value": 1.0, "source": "simulated:oracle"}
    return [json.dumps(header), json.dumps({**event, "session": "old/board0", "seq": 0})]


@pytest.mark.parametrize(
    ("tail", "message"),
    [
        ('{"time": 0.4, "step": 1, "episo\n', ":3: corrupt line"),  # a line cut in the middle
        ('{"time": 0.4, "value": 1.0}\n', ":3: corrupt feedback event, missing"),
        ("not json at all\n", ":3: corrupt line"),
    ],
)
def test_a_corrupt_log_is_one_line_before_the_run(compose_train, tmp_path, tail, message) -> None:
    log = tmp_path / "feedback.jsonl"
    log.write_text("\n".join(_log_lines()) + "\n" + tail)
    with pytest.raises(ConfigError) as err:
        compose_train(*CARTPOLE, *TINY, "trainer=replay", f"trainer.log={log}")
    text = str(err.value)
    assert text.startswith(f"trainer.log={str(log)!r} cannot be replayed: ") and message in text
    assert "\n" not in text


def test_a_readable_log_is_accepted_and_a_missing_one_refused(compose_train, tmp_path) -> None:
    log = tmp_path / "feedback.jsonl"
    log.write_text("\n".join(_log_lines()) + "\n")
    cfg = compose_train(*CARTPOLE, *TINY, "trainer=replay", f"trainer.log={log}")
    assert cfg.trainer.name == "replay"
    with pytest.raises(ConfigError, match="is not a file"):
        compose_train(*CARTPOLE, *TINY, "trainer=replay", f"trainer.log={tmp_path / 'none.jsonl'}")
