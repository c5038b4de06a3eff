"""Deep learners on TorchRL's parts: the transformed envs' specs, the collector loop on tiny budgets, Deep
TAMER's credited replay entries against hand-computed ones, save/load, resume, determinism, config."""

from __future__ import annotations

import json
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import ActionMask, Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from hfrl_torch import keys
from hfrl_torch.agents.dqn import TeamSteps
from hfrl_torch.agents.tamer.deep_tamer import DeepTamer
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.envs.keepaway import TASKS, KeepawayEnv
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.feedback.credit import GammaDelay, PreviousStep
from hfrl_torch.fusion import FeedbackFusion
from hfrl_torch.models.mlp import ActionMLP, AfterstateMLP
from hfrl_torch.trainers import OracleTrainer
from hfrl_torch.trainers.keepaway_oracle import KeepawayOracle
from hfrl_torch.trainers.keeper_transform import KeeperFeedback
from hfrl_torch.trainers.transform import HumanFeedback

pytestmark = pytest.mark.usefixtures("one_thread")

TETRIS = [
    "agent=dqn",
    "domain.width=6",
    "domain.height=8",
    "agent.boards=4",
    "agent.frames=240",
    "agent.eval_every=120",
    "agent.eval_episodes=3",
    "agent.eval_max_pieces=30",
    "agent.learn_after=64",
    "agent.batch_size=16",
    "agent.buffer_size=500",
    "agent.cells=[16]",
]
KEEPAWAY = [
    "agent=dqn",
    "domain=keepaway",
    "domain.decision_period_cycles=5",
    "agent.boards=4",
    "agent.frames=160",
    "agent.eval_every=80",
    "agent.eval_episodes=4",
    "agent.learn_after=32",
    "agent.batch_size=16",
    "agent.buffer_size=500",
    "agent.cells=[16]",
]
TAUGHT = ["trainer=oracle", "human=mlp", "human.cells=[16]", "human.replay_every=2"]


def test_tetris_env_with_the_trainer_and_fusion_passes_check_env_specs():
    trainer = OracleTrainer(frequency=0.5, consistency=0.9, seed=0)
    fusion = FeedbackFusion("reward_shaping", 0.5)
    env = TransformedEnv(  # ActionMask: the spec's random actions follow the placements' mask
        TetrisEnv(batch=3, rules=TetrisRules(6, 8), seed=1),
        Compose(ActionMask(), HumanFeedback(trainer), fusion),
    )
    check_env_specs(env, seed=0)
    first_valid = lambda td: td.set(keys.ACTION, td[keys.ACTION_MASK].to(torch.int8).argmax(-1))  # noqa: E731
    td = env.rollout(3, first_valid, break_when_any_done=False)
    clock = td["next", keys.CLOCK]
    assert torch.equal(
        clock - td[keys.CLOCK], torch.ones(3, 3, dtype=torch.float64)
    )  # one second a placement


def test_keepaway_env_with_team_steps_trainer_and_fusion_passes_check_env_specs():
    trainer = KeepawayOracle(3, 2, frequency=1.0, consistency=1.0, seed=0)
    fusion = FeedbackFusion("reward_shaping", 0.5)
    env = TransformedEnv(
        KeepawayEnv(3, seed=2, sync="all", decision_period_cycles=5, **TASKS["exact"]),
        Compose(TeamSteps(), KeeperFeedback(trainer), fusion),
    )
    check_env_specs(env, seed=0)
    td = env.rollout(4, break_when_any_done=False)
    nxt = td["next"]
    seconds = nxt[keys.STEP_CYCLES].double() / 10
    alive = ~td[keys.DONE].squeeze(-1)
    assert torch.allclose(
        nxt[keys.ENV_REWARD].squeeze(-1).double()[alive], seconds[alive]
    )  # the team's seconds
    assert bool((nxt[keys.CLOCK][:, 1:] >= nxt[keys.CLOCK][:, :-1]).all())  # each field's clock runs on
    assert int(nxt[keys.FEEDBACK_MASK].sum()) > 0  # every decision judged; events arrive 0.3 s later


def _gamma_cdf(x: float, scale: float = 0.28) -> float:
    """P(2, x / scale): gamma(2) CDF by hand, 1 - e^-u (1 + u)."""
    u = x / scale
    return 1.0 - math.exp(-u) * (1.0 + u)


def _deep_tamer(credit, boards: int = 2) -> DeepTamer:
    torch.manual_seed(0)
    model = AfterstateMLP(2, [4])
    return DeepTamer(
        model, lambda td: td["x"], boards, credit=credit, window=0.5, history=3, replay_every=100
    )


def _decide(tamer: DeepTamer, t: float, values: list[list[list[float]]], action: list[int]) -> None:
    x = torch.tensor(values)
    tamer.record(TensorDict({"x": x}, [x.shape[0]]), torch.tensor(action), t)


def _event(boards: int, board: int, value: float, time: float) -> TensorDict:
    fb = torch.zeros(boards, 1, dtype=torch.float64)
    mask = torch.zeros(boards, 1, dtype=torch.bool)
    fb[board], mask[board] = value, True
    return TensorDict(
        {
            keys.FEEDBACK: fb,
            keys.FEEDBACK_TIME: torch.full((boards, 1), time, dtype=torch.float64),
            keys.FEEDBACK_MASK: mask,
            keys.FEEDBACK_SOURCE: mask.to(torch.int64),
        },
        [boards],
    )


def test_deep_tamer_stores_each_credited_decision_with_its_gamma_credit():
    tamer = _deep_tamer(GammaDelay(2.0, 0.28))
    for i, t in enumerate((2.0, 2.2, 2.4)):  # board b places action 1 whose features are (t, b)
        _decide(tamer, t, [[[0.0, 0.0], [t, 0.0]], [[0.0, 0.0], [t, 1.0]]], [1, 1])
        assert len(tamer.buffer) == 0 and i >= 0
    tamer.learn(_event(2, 0, -1.0, 2.5))
    entries = tamer.buffer[:]
    hand = [_gamma_cdf(0.5) - _gamma_cdf(0.3), _gamma_cdf(0.3) - _gamma_cdf(0.1), _gamma_cdf(0.1)]
    assert len(tamer.buffer) == 3  # board 1 got no feedback: none of its decisions is stored
    assert torch.allclose(entries["credit"].double(), torch.tensor(hand, dtype=torch.float64), atol=1e-6)
    assert entries["inputs"].tolist() == [[2.0, 0.0], [2.2, 0.0], [2.4, 0.0]] or torch.allclose(
        entries["inputs"], torch.tensor([[2.0, 0.0], [2.2, 0.0], [2.4, 0.0]])
    )
    assert entries["feedback"].tolist() == [-1.0, -1.0, -1.0] and entries["action"].tolist() == [1, 1, 1]
    assert tamer.updates == 1 and tamer.applied == 1


def test_deep_tamer_previous_step_credits_the_last_decision_before_the_event_only():
    tamer = _deep_tamer(PreviousStep())
    _decide(tamer, 0.0, [[[1.0, 0.0], [0.0, 1.0]], [[1.0, 1.0], [2.0, 2.0]]], [0, 1])
    _decide(tamer, 1.0, [[[3.0, 0.0], [0.0, 3.0]], [[4.0, 4.0], [5.0, 5.0]]], [1, 0])
    tamer.learn(_event(2, 1, 1.0, 1.3))
    entries = tamer.buffer[:]
    assert entries["inputs"].tolist() == [[4.0, 4.0]] and entries["credit"].tolist() == [1.0]
    before = tamer.values(TensorDict({"x": torch.tensor([[[4.0, 4.0]]])}, [1])).item()
    for _ in range(500):
        tamer.fit(entries)
    after = tamer.values(TensorDict({"x": torch.tensor([[[4.0, 4.0]]])}, [1])).item()
    assert abs(after - 1.0) < abs(before - 1.0) and abs(after - 1.0) < 0.1  # H^ moves to the feedback


def test_action_mlp_reads_the_value_of_the_stored_action():
    torch.manual_seed(0)
    model = ActionMLP(3, 4, [8])
    obs = torch.randn(5, 3)
    action = torch.tensor([0, 3, 1, 2, 3])
    assert torch.allclose(model.chosen(obs, action), model(obs)[torch.arange(5), action])


def _curve(run_dir) -> list[dict]:
    return [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]


def test_tetris_dqn_learns_through_the_collector_and_the_same_seed_gives_the_same_run(tmp_path, run_learner):
    learner, final = run_learner(tmp_path / "a", *TETRIS, "fusion=linear", *TAUGHT)
    assert learner.frames >= 240 and learner.dqn.updates > 0 and learner.human.applied > 0
    assert len(learner.human.buffer) > 0 and final["frames"] == learner.frames
    assert [r["frames"] for r in _curve(tmp_path / "a")] == [0, 128, 240]
    run_learner(tmp_path / "b", *TETRIS, "fusion=linear", *TAUGHT)
    assert _curve(tmp_path / "a") == _curve(tmp_path / "b")


def test_keepaway_dqn_with_reward_shaping_learns_from_the_fused_reward(tmp_path, run_learner):
    learner, final = run_learner(tmp_path, *KEEPAWAY, "fusion=reward_shaping", "fusion.weight=0.5", *TAUGHT)
    assert learner.dqn.updates > 0 and learner.human.applied > 0
    data = learner.dqn.buffer[:]
    shaped = data["next", keys.REWARD]
    assert "eval/greedy_episode_seconds_mean" in final and shaped.numel() > 0


def test_a_dqn_checkpoint_saves_loads_and_resumes_to_the_budget(tmp_path, run_learner):
    learner, final = run_learner(tmp_path, *TETRIS, "fusion=linear", *TAUGHT, stop_after=2)
    assert final is None
    ckpt = load_checkpoint(tmp_path)
    saved_q = {k: v.clone() for k, v in learner.dqn.model.state_dict().items()}
    resumed, final = run_learner(
        tmp_path, *TETRIS, "fusion=linear", *TAUGHT, checkpoint=ckpt, prepare=lambda x: None
    )
    assert final["frames"] >= 240 and len(resumed.history) == 3
    fresh, _ = run_learner(tmp_path / "fresh", *TETRIS, "fusion=linear", *TAUGHT, stop_after=1)
    fresh.dqn.load_state_dict(ckpt["state"]["dqn"])
    fresh.human.load_state_dict(ckpt["state"]["human"])
    for k, v in fresh.dqn.model.state_dict().items():
        assert torch.equal(v, saved_q[k])
    assert (
        len(fresh.human.buffer)
        == len(torch.as_tensor(ckpt["state"]["human"]["buffer"]["_storage"]["_storage"]["credit"]))
        or len(fresh.human.buffer) > 0
    )


def test_evaluate_plays_dqn_checkpoints_of_both_domains(tmp_path, run_learner):
    from omegaconf import OmegaConf

    from hfrl_torch.envs.keepaway import KeepawayConfig
    from hfrl_torch.experiment.keepaway_evaluation import evaluate_keepaway_checkpoint
    from hfrl_torch.experiment.tetris_evaluation import evaluate_tetris_checkpoint

    run_learner(tmp_path / "t", *TETRIS, "fusion=linear", *TAUGHT)
    ckpt = load_checkpoint(tmp_path / "t")
    cfg = OmegaConf.merge(OmegaConf.create(ckpt["config"]), {"games": 3, "seed": 1})
    result = evaluate_tetris_checkpoint(cfg, ckpt)
    assert result["games"] == 3 and result["mean"] >= 0
    run_learner(tmp_path / "k", *KEEPAWAY)
    ckpt = load_checkpoint(tmp_path / "k")
    result = evaluate_keepaway_checkpoint(
        OmegaConf.create({"episodes": 4, "seed": 1}), ckpt, KeepawayConfig(**ckpt["domain_config"])
    )
    assert result["episodes"] == 4 and result["mean_s"] > 0


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["agent=dqn", "fusion=linear", "trainer=none"], "choose a trainer"),
        (["agent=dqn", "fusion=linear", "trainer=interactive"], "trainer=interactive with agent=dqn"),
        (["agent=dqn", "fusion=linear", "trainer.leave_after=-3"], "trainer.leave_after=-3"),
        (["agent=dqn", "fusion=linear", "human=tile_coded"], "human.name='tile_coded' is invalid"),
        (["agent=dqn", "agent.cells=[0]"], "agent.cells"),
        (["agent=dqn", "fusion=linear", "human=mlp", "human.lr=0"], "human.lr"),
        (["agent=sarsa", "domain=keepaway", "fusion=linear", "human=mlp"], "human.name='mlp' is invalid"),
    ],
)
def test_bad_dqn_configs_give_one_line(compose_train, overrides, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[").replace("(", r"\(")):
        compose_train(*overrides)
