"""``domain=gym``: any Gymnasium task (or a user's TorchRL env) through train.py's loop and evaluate.py, the
oracle against a user's reference policy, and the one-line errors before a run starts (issue 42)."""

from __future__ import annotations

import os

import pytest
import torch
from gym_task_helpers import make_countdown, walk_right, walk_right_values
from tensordict import TensorDict
from torchrl.envs import check_env_specs

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.envs.gym_task import GymTask, make_gym_batch, task_spaces
from hfrl_torch.experiment.cli import CHECKED, compose_config, precheck
from hfrl_torch.experiment.config import validate_train
from hfrl_torch.experiment.gym_evaluation import evaluate_gym
from hfrl_torch.experiment.learners.gym_dqn import gym_env
from hfrl_torch.feedback.log import load_feedback_log
from hfrl_torch.trainers.reference_oracle import ReferenceOracle

HELPERS = "tests.experiment.gym_task_helpers"
CARTPOLE = ("domain=gym", "domain.env_id=CartPole-v1", "agent=dqn")
TINY = (
    "agent.boards=4",
    "agent.steps_per_batch=8",
    "agent.learn_after=64",
    "agent.frames_per_update=4",
    "agent.epsilon_frames=400",
    "agent.eval_episodes=4",
)


def test_the_batched_envs_pass_torchrl_spec_checks(one_thread) -> None:
    env = gym_env(GymTask("CartPole-v1"), 3, seed=0)
    check_env_specs(env)
    assert env.batch_size == torch.Size([3]) and env.action_spec.space.n == 2
    own = make_gym_batch(GymTask(make=make_countdown), 2, seed=0)  # a user's unbatched EnvBase, twice
    check_env_specs(own)
    spaces = task_spaces(GymTask(make=make_countdown))
    assert (spaces.observation_size, spaces.actions) == (1, 2)


@pytest.mark.parametrize("reference", [walk_right, walk_right_values])
def test_the_oracle_judges_against_the_reference_at_its_consistency(reference) -> None:
    n, consistency = 4000, 0.8
    oracle = ReferenceOracle(reference, 2, frequency=1.0, consistency=consistency, seed=3)
    obs = TensorDict({"observation": torch.rand(n, 2)}, [n])
    for action, sign in ((1, 1.0), (0, -1.0)):
        events = oracle.give(obs, torch.full((n,), action), 1.0, torch.zeros(n, dtype=torch.int64))
        values = torch.tensor([e[0].value for e in events])
        assert all(len(e) == 1 for e in events) and events[0][0].time == pytest.approx(1.3)
        assert abs(float((values == sign).double().mean()) - consistency) < 0.03
    sparse = ReferenceOracle(reference, 2, frequency=0.25, consistency=1.0, seed=4)
    given = sparse.give(obs, torch.ones(n, dtype=torch.int64), 0.0, torch.zeros(n, dtype=torch.int64))
    assert abs(sum(map(len, given)) / n - 0.25) < 0.03


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("domain.env_id=NoSuchTask-v0",), "domain.env_id='NoSuchTask-v0' is not a Gymnasium task"),
        (("domain.env_id=Pendulum-v1",), "continuous action space"),
        (("domain.make=tests.experiment.no_such_module:make",), "does not import"),
        (("fusion=linear", "trainer=oracle"), "needs trainer.reference="),
        (("fusion=linear", "trainer.reference=examples.nope:reference"), "does not import"),
        (("fusion=linear", f"trainer.reference={HELPERS}:wrong_shape"), "of shape []"),
        (("fusion=linear", f"trainer.reference={HELPERS}:absent"), "has no 'absent'"),
        (
            (f"domain.make={HELPERS}:make_grid_corridor",),
            "allowed: a vector (Box of one dimension) or a frame",
        ),
        (
            ("fusion=linear", "trainer=value_proxy"),
            "trainer=value_proxy on domain=gym needs trainer.reference",
        ),
        (
            ("fusion=linear", "trainer=value_proxy", "trainer.reference=examples.cartpole:reference"),
            "needs float",
        ),
    ],
)
def test_bad_input_is_one_line_before_the_run(compose_train, overrides, message) -> None:
    with pytest.raises(ConfigError) as err:
        compose_train(*CARTPOLE, *overrides)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_users_own_task_trains_and_evaluates_with_no_edit_in_the_package(run_learner, tmp_path) -> None:
    own = (f"domain.make={HELPERS}:make_corridor", "fusion=linear", f"trainer.reference={HELPERS}:walk_right")
    learner, final = run_learner(
        tmp_path,
        "domain=gym",
        "agent=dqn",
        "domain.min_return=-30",
        *own,
        *TINY,
        "agent.frames=256",
        "agent.eval_every=128",
    )
    assert final["frames"] == 256 and learner.events > 100
    assert learner.episodes > 0 and final["eval/greedy_return_mean"] <= -5.0  # at least 5 steps to the end
    cfg = compose_config("evaluate", "domain=gym", f"policy={tmp_path}", "episodes=3")
    result = evaluate_gym(cfg)
    assert result["task"].endswith("make_corridor") and result["episodes"] == 3


@pytest.mark.parametrize("agent", ["dqn", "tamer"])
def test_a_task_seen_as_frames_trains_cnns_and_plays_back(run_learner, tmp_path, one_thread, agent) -> None:
    """Frames ([16, 16, 1] uint8) give DQN's Q and Deep TAMER's H^ as CNNs; the saved policy names the
    frame's shape, so evaluate.py rebuilds the CNN and plays it."""
    learner, final = run_learner(
        tmp_path,
        "domain=gym",
        f"agent={agent}",
        f"domain.make={HELPERS}:make_pixel_corridor",
        "domain.min_return=-30",
        f"trainer.reference={HELPERS}:walk_right",
        *(("fusion=linear", *TINY) if agent == "dqn" else ("trainer=oracle", "agent.boards=4")),
        "agent.frames=128",
        "agent.eval_every=128",
        "agent.eval_episodes=2",
        "human.batch_size=8",
    )
    assert final["frames"] == 128 and learner.events > 10
    assert learner.spaces.frame == (16, 16, 1)
    assert type(learner.human.model).__name__ == "ActionCNN"
    saved = load_checkpoint(tmp_path)["policy"]
    assert saved["observation_shape"] == [16, 16, 1]
    result = evaluate_gym(compose_config("evaluate", "domain=gym", f"policy={tmp_path}", "episodes=2"))
    assert result["task"].endswith("make_pixel_corridor") and result["episodes"] == 2


def test_the_value_proxy_judges_by_a_saved_runs_action_values(run_learner, tmp_path, one_thread) -> None:
    """``trainer=value_proxy``: a callable's action values, then a saved run's (its Q), give the feedback a
    fused DQN learns from; the corridor's values say right is better, so the events are +1 and -1."""
    own = (f"domain.make={HELPERS}:make_corridor", "domain.min_return=-30", *TINY, "agent.eval_every=128")
    proxy = ("fusion=linear", "trainer=value_proxy", "trainer.timing.enabled=false", "agent.frames=128")
    values = f"trainer.reference={HELPERS}:walk_right_values"
    learner, final = run_learner(tmp_path / "callable", "domain=gym", "agent=dqn", *own, *proxy, values)
    events = load_feedback_log(tmp_path / "callable" / "feedback.jsonl")
    assert final["frames"] == 128 and len(events) > 50  # one event a step (no step without a better action)
    assert {e.value for e in events} == {1.0, -1.0} and {e.source for e in events} == {
        "simulated:value_proxy"
    }
    assert learner.human.applied > 0
    run_learner(tmp_path / "saved", "domain=gym", "agent=dqn", *own, "agent.frames=128")
    judged, final = run_learner(
        tmp_path / "judged",
        "domain=gym",
        "agent=dqn",
        *own,
        *proxy,
        f"trainer.reference={tmp_path / 'saved'}",
    )
    assert final["frames"] == 128 and judged.human.applied > 0


def test_fused_dqn_on_cartpole_beats_random_resumes_and_plays_back(run_learner, tmp_path, one_thread) -> None:
    taught = (*CARTPOLE, "fusion=linear", "trainer.reference=examples.cartpole:reference", *TINY)
    budget = (
        "agent.frames=768",
        "agent.eval_every=384",
        "fusion.weight=1.0",  # a fixed weight: eq. 4.4's trust needs more episodes than this to rise
        "human.lr=0.005",
        "human.replay_every=2",
        "trainer.frequency=1.0",
        "trainer.timing.enabled=false",
    )
    _, stopped = run_learner(tmp_path, *taught, *budget, stop_after=2)  # two points, then "Ctrl-C"
    assert stopped is None
    learner, final = run_learner(tmp_path, *taught, *budget, checkpoint=load_checkpoint(tmp_path))
    assert learner.resumed and final["frames"] == 768
    assert [r["frames"] for r in learner.history] == [0, 384, 768]
    random = evaluate_gym(compose_config("evaluate", "domain=gym", "policy=random", "episodes=8"))
    played = evaluate_gym(compose_config("evaluate", "domain=gym", f"policy={tmp_path}", "episodes=8"))
    assert final["eval/greedy_return_mean"] > 1.5 * random["mean"]
    assert played["mean"] > 1.5 * random["mean"] and played["plays"].startswith("DQN, Q fused with H^")


def test_a_users_config_dir_adds_a_domain_option_that_the_check_before_the_run_accepts(
    tmp_path, monkeypatch
) -> None:
    """``train.py --config-dir <dir> domain=<their file>``: the check before the run searches the user's
    directory as Hydra does (without it, the option is unknown, in one line)."""
    monkeypatch.delenv(CHECKED, raising=False)
    (tmp_path / "conf" / "domain").mkdir(parents=True)
    (tmp_path / "conf" / "domain" / "mytask.yaml").write_text(
        "defaults:\n  - gym\n  - _self_\nenv_id: CartPole-v1\nmax_episode_steps: 50\n"
    )
    job = ["domain=mytask", "agent=dqn", "human=mlp", f"hydra.run.dir={tmp_path / 'run'}"]
    with pytest.raises(SystemExit) as stopped:
        precheck(job, "train", validate_train)
    assert stopped.value.code == 2
    precheck(["--config-dir", str(tmp_path / "conf"), *job], "train", validate_train)
    assert os.environ.get(CHECKED) == "1"  # every job checked, none refused
    with pytest.raises(SystemExit):  # a bad value of the user's domain is still refused
        precheck(
            ["--config-dir", str(tmp_path / "conf"), *job, "domain.env_id=NoSuch-v0"], "train", validate_train
        )
