"""``domain=gym agent=tamer``: Deep TAMER's H^ alone, taught by the simulated oracle, on any task; the trainer
leaving freezes H^; a resumed run equals the uninterrupted one; a saved gym policy as the oracle's reference;
the one-line errors before a run directory (issue 42)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.common.checkpoint import load_checkpoint, save_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment.cli import CHECKED, compose_config, precheck
from hfrl_torch.experiment.config import validate_train
from hfrl_torch.experiment.factories import PolicyReference, make_gym_reference
from hfrl_torch.experiment.gym_evaluation import evaluate_gym
from hfrl_torch.experiment.learners.gym_tamer import GymTamer
from hfrl_torch.models.mlp import ActionMLP
from hfrl_torch.trainers.reference_oracle import ReferenceOracle

CARTPOLE = ("domain=gym", "domain.env_id=CartPole-v1", "agent=tamer", "trainer=oracle")
SCRIPTED = "trainer.reference=examples.cartpole:reference"
TINY = (
    SCRIPTED,
    "domain.max_episode_steps=200",  # a greedy point costs at most 200 steps of its episodes
    "agent.boards=4",
    "agent.eval_episodes=4",
    "human.cells=[32]",
    "human.lr=0.01",
    "human.replay_every=1",
    "trainer.frequency=1.0",
    "trainer.timing.enabled=false",
)
RANDOM_RETURN = 22.0  # CartPole-v1 under uniformly random actions (about 22 a episode)


def _h_weights(learner) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in learner.human.model.state_dict().items()}


def _final(learner) -> dict:
    """A result to report on: the learner's point now."""
    return learner._point().record


def _same(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    return a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


def test_tamer_alone_on_cartpole_beats_random_and_evaluate_plays_its_policy(
    run_learner, tmp_path, one_thread
):
    learner, final = run_learner(tmp_path, *CARTPOLE, *TINY, "agent.frames=800", "agent.eval_every=400")
    assert [r["frames"] for r in learner.history] == [0, 400, 800]
    assert learner.events > 300 and learner.left_at is None
    assert final["eval/greedy_return_mean"] > 3 * RANDOM_RETURN
    ckpt = load_checkpoint(tmp_path)
    assert (ckpt["agent"], ckpt["policy"]["kind"]) == ("tamer", "gym_tamer")
    played = evaluate_gym(compose_config("evaluate", "domain=gym", f"policy={tmp_path}", "episodes=8"))
    assert played["plays"] == "TAMER, greedy on H^" and played["mean"] > 3 * RANDOM_RETURN
    lines = (tmp_path / "feedback.jsonl").read_text().splitlines()
    assert len(lines) >= learner.events  # every event given is logged (some were still on their way)


def test_the_trainer_leaving_freezes_h_and_it_keeps_acting(run_learner, tmp_path, one_thread):
    snapshot: dict[str, dict[str, torch.Tensor]] = {}

    def watch(learner) -> None:
        step = learner._step

        def step_and_watch() -> None:
            if not learner.present and "left" not in snapshot:
                snapshot["left"] = _h_weights(learner)
            step()

        learner._step = step_and_watch
        snapshot["start"] = _h_weights(learner)

    leave = ("trainer.leave_after=0.1", "trainer.leave_unit=minutes")  # 6 simulated seconds: 30 steps
    learner, final = run_learner(
        tmp_path, *CARTPOLE, *TINY, *leave, "agent.frames=400", "agent.eval_every=100", prepare=watch
    )
    assert learner.left_at == 120 and not learner.present
    assert not _same(snapshot["start"], snapshot["left"])  # H^ learned while the trainer watched
    assert _same(snapshot["left"], _h_weights(learner))  # and not at all after
    after = [r for r in learner.history if r["frames"] >= 200]
    assert len(after) == 3 and {r["trainer/present"] for r in after} == {0.0}
    assert len({r["feedback_events"] for r in after}) == 1  # no feedback once gone
    assert len({r["eval/greedy_return_mean"] for r in after}) == 1  # the frozen H^ plays the same episodes
    assert after[-1]["eval/greedy_return_mean"] > RANDOM_RETURN
    ended = learner.episodes
    assert ended > 0 and final["train/episodes"] == ended  # it kept acting: episodes ended after the leave


def test_a_resumed_run_equals_the_uninterrupted_one(run_learner, tmp_path, one_thread):
    budget = (*CARTPOLE, *TINY, "agent.frames=200", "agent.eval_every=100")
    whole, _ = run_learner(tmp_path / "whole", *budget)
    _, stopped = run_learner(tmp_path / "cut", *budget, stop_after=2)  # two points, then "Ctrl-C"
    assert stopped is None
    resumed, _ = run_learner(tmp_path / "cut", *budget, checkpoint=load_checkpoint(tmp_path / "cut"))
    assert resumed.resumed and resumed.restarts == 0
    assert json.dumps(resumed.history) == json.dumps(whole.history)  # (NaN where no episode ended yet)
    assert _same(_h_weights(resumed), _h_weights(whole))
    assert torch.equal(resumed.td[keys.OBSERVATION], whole.td[keys.OBSERVATION])
    logged = [(tmp_path / run / "feedback.jsonl").read_text().splitlines() for run in ("whole", "cut")]
    events = [
        [{k: v for k, v in e.items() if k != "session"} for e in map(json.loads, log) if "value" in e]
        for log in logged
    ]
    assert events[0] == events[1]  # the resumed log has each event once, as the uninterrupted one


def test_a_task_that_does_not_replay_the_same_restarts_its_episodes(compose_train, tmp_path, one_thread):
    cfg = compose_train("logger.backend=none", *CARTPOLE, *TINY, "agent.frames=200", "agent.eval_every=100")
    first = GymTamer(cfg, tmp_path, None)
    for _ in range(10):
        first._step()
    saved = first.checkpoint()
    first.close()
    saved["state"]["observation"] = saved["state"]["observation"] + 1.0  # not where the replay ends
    again = GymTamer(cfg, tmp_path, {**saved, "history": []})
    assert again.restarts == 1 and again.played == [] and again.steps == 10
    again._step()
    assert len(again.played) == 1 and any(
        "did not replay the same" in line for line in again.report(_final(again))
    )
    again.close()


# ----------------------------------------------------------------------------- a saved policy as reference


def _saved_gym_policy(path: Path, observation_size: int = 4, actions: int = 2, seed: int = 0) -> ActionMLP:
    """A ``domain=gym`` DQN checkpoint (Q alone) of a random network at ``path``; returns the network."""
    torch.manual_seed(seed)
    q = ActionMLP(observation_size, actions, [8], [1.0] * observation_size)
    policy = export_policy(
        "gym_dqn",
        task={"name": "gym", "env_id": "CartPole-v1", "make": None, "max_episode_steps": None},
        observation_size=observation_size,
        actions=actions,
        scale=[1.0] * observation_size,
        cells=[8],
        q=q.state_dict(),
        fusion=None,
        human=None,
    )
    save_checkpoint(
        path, domain="gym", agent="dqn", config_yaml="", payload={"policy": policy, "history": []}
    )
    return q


def test_the_oracle_judges_against_a_checkpoints_greedy_policy(compose_train, tmp_path):
    q = _saved_gym_policy(tmp_path / "run" / "checkpoints" / "last.pt")
    for named in (tmp_path / "run", tmp_path / "run" / "checkpoints" / "last.pt"):  # a run dir or its file
        cfg = compose_train(*CARTPOLE, f"trainer.reference={named}")
        reference = make_gym_reference(cfg)
        assert isinstance(reference, PolicyReference)
        obs = torch.randn(500, 4) * torch.tensor([1.0, 2.0, 0.2, 2.0])
        greedy = q(obs).argmax(-1)
        assert torch.equal(reference(obs), greedy) and len(set(greedy.tolist())) == 2
        oracle = ReferenceOracle(reference, 2, frequency=1.0, consistency=1.0, seed=1)
        td = TensorDict({keys.OBSERVATION: obs}, [500])
        for action in (0, 1):
            events = oracle.give(td, torch.full((500,), action), 0.0, torch.zeros(500, dtype=torch.int64))
            values = torch.tensor([e[0].value for e in events])
            assert torch.equal(values, torch.where(greedy == action, 1.0, -1.0))


def test_a_tamer_run_teaches_with_a_trained_run_as_its_reference(run_learner, tmp_path, one_thread):
    """A gym run's own checkpoint (here a TAMER run taught by the scripted policy) as the next reference."""
    run_learner(tmp_path / "teacher", *CARTPOLE, *TINY, "agent.frames=400", "agent.eval_every=400")
    taught = [o for o in TINY if o != SCRIPTED]
    learner, final = run_learner(
        tmp_path / "pupil",
        *CARTPOLE,
        *taught,
        f"trainer.reference={tmp_path / 'teacher'}",
        "agent.frames=400",
        "agent.eval_every=400",
    )
    assert learner.events > 100 and final["eval/greedy_return_mean"] > 2 * RANDOM_RETURN


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("trainer=none",), "TAMER alone learns only from a trainer's feedback; choose trainer=oracle"),
        ((SCRIPTED, "fusion=linear", "trainer=oracle"), "TAMER acts on H^ alone; use fusion=none"),
        (("trainer=interactive",), "agent=tamer (trainer=interactive picks fusion=linear unless told)"),
        (("trainer=replay",), "trainer=replay needs trainer.log=<feedback log file>"),
        ((SCRIPTED, "human=linear"), "human.name='linear' is invalid"),
        (("trainer.reference=examples.nope:reference",), "does not import"),
        (("trainer.reference=tests.experiment.gym_task_helpers:wrong_shape",), "of shape []"),
        (("trainer.reference=runs/no_such_run",), "is not a checkpoint of a domain=gym run"),
        ((SCRIPTED, "agent.eval_every=0"), "agent.eval_every=0 is invalid"),
        ((SCRIPTED, "trainer.leave_after=-1"), "trainer.leave_after=-1 is invalid"),
    ],
)
def test_bad_input_is_one_line(compose_train, overrides, message) -> None:
    with pytest.raises(ConfigError) as err:
        compose_train(*CARTPOLE, *overrides)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_a_bad_reference_checkpoint_is_one_line_before_any_run_directory(
    compose_train, tmp_path, monkeypatch
) -> None:
    monkeypatch.delenv(CHECKED, raising=False)
    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("not a checkpoint")
    _saved_gym_policy(tmp_path / "mountain_car.pt", observation_size=2, actions=3)  # another env's sizes
    _saved_gym_policy(tmp_path / "three_actions.pt", observation_size=4, actions=3)
    save_checkpoint(tmp_path / "tetris.pt", domain="tetris", agent="cem", config_yaml="", payload={})
    cases = {
        not_a_checkpoint: "is not a checkpoint of a domain=gym run (checkpoint",
        tmp_path
        / "mountain_car.pt": "plays observations of size 2 with 3 actions; domain.env_id='CartPole-v1'",
        tmp_path / "three_actions.pt": "has observations of size 4 and 2 actions",
        tmp_path / "tetris.pt": "is for domain 'tetris', not 'gym'",
    }
    run_dir = tmp_path / "run"
    for path, message in cases.items():
        with pytest.raises(ConfigError) as err:
            compose_train(*CARTPOLE, f"trainer.reference={path}")
        assert message in str(err.value) and "\n" not in str(err.value)
        with pytest.raises(SystemExit) as stopped:
            precheck(
                [*CARTPOLE, f"trainer.reference={path}", f"hydra.run.dir={run_dir}"], "train", validate_train
            )
        assert stopped.value.code == 2 and not run_dir.exists()
