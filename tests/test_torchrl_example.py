"""The documented TorchRL example: a collector over ``TransformedEnv(env, Compose(HumanFeedback,
FeedbackFusion))`` and a learner training on the fused reward, with a tiny budget; and the transform pair."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import torch
from torchrl.envs import ActionMask, Compose, TransformedEnv
from torchrl.envs.utils import check_env_specs

from hfrl_torch import keys
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.fusion import FeedbackFusion
from hfrl_torch.trainers import OracleTrainer
from hfrl_torch.trainers.transform import HumanFeedback

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "torchrl_collector.py"


def _example():
    spec = importlib.util.spec_from_file_location("torchrl_collector", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_collector_example_trains_on_the_fused_reward():
    example = _example()
    shaped = example.train(frames=800, weight=0.5, boards=4, steps=20, seed=1)
    plain = example.train(frames=800, weight=0.0, boards=4, steps=20, seed=1)
    assert shaped["feedback_events"] > 100 and shaped["shaping_total"] != 0.0
    assert plain["shaping_total"] == 0.0 and plain["feedback_events"] > 100  # the trainer speaks; w = 0
    assert shaped["games"] > 0 and plain["games"] > 0


def _env(weight: float = 0.5) -> TransformedEnv:
    trainer = OracleTrainer(frequency=1.0, consistency=1.0, seed=0, reaction=0.3)
    fusion = FeedbackFusion("reward_shaping", weight, estimate_key=None, feedback_key=keys.FEEDBACK)
    # ActionMask first: the transformed env's own action spec then follows the env's mask (for rand_action)
    return TransformedEnv(
        TetrisEnv(batch=3, rules=TetrisRules(6, 6)), Compose(ActionMask(), HumanFeedback(trainer), fusion)
    )


def test_human_feedback_and_feedback_fusion_pass_check_env_specs_and_fuse_each_steps_feedback():
    check_env_specs(_env())
    env = _env()
    td = env.reset()
    assert td[keys.FEEDBACK].shape == (3, 4) and not td[keys.FEEDBACK_MASK].any()
    td.set(keys.ACTION, torch.zeros(3, dtype=torch.int64))
    nxt = env.step(td)["next"]
    # the oracle judged every board's placement 0.3 s after it; one placement lasts 1 s: due in this step
    assert nxt[keys.FEEDBACK_MASK][:, 0].all() and nxt[keys.FEEDBACK_TIME][:, 0].tolist() == [0.3] * 3
    fb = nxt[keys.FEEDBACK][:, 0]
    assert set(fb.tolist()) <= {-1.0, 1.0}
    torch.testing.assert_close(
        nxt[keys.REWARD].reshape(-1), nxt[keys.ENV_REWARD].reshape(-1) + 0.5 * fb.float()
    )


def test_the_transform_state_resumes_its_clock_and_trainer():
    env = _env()
    td = env.reset()
    for _ in range(3):
        td.set(keys.ACTION, torch.zeros(3, dtype=torch.int64))
        td = env.step(td)["next"]
    state = env.transform[1].state_dict()
    again = _env()
    again.transform[1].load_state_dict(state)
    assert again.transform[1].steps == 3 and again.transform[1].clock == 3.0
