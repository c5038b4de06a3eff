"""``domain=gym agent=ppo``: PPO through train.py's loop and evaluate.py, alone and fused with the oracle by
every scheme that can act on a softmax policy, kill-safe resume, and the one-line errors (issue 42)."""

from __future__ import annotations

import math
import shutil
from collections.abc import Mapping
from typing import Any

import pytest
import torch
from script_runner import run_script

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.experiment.gym_evaluation import evaluate_gym

CARTPOLE = ("domain=gym", "domain.env_id=CartPole-v1", "agent=ppo")
TINY = (  # 128 frames a batch, one minibatch, larger steps than the default's: learns in 2,048 frames
    "agent.boards=4",
    "agent.steps_per_batch=32",
    "agent.eval_episodes=4",
    "agent.lr=0.001",
    "agent.epochs=4",
)
TAUGHT = (
    "trainer=oracle",
    "trainer.reference=examples.cartpole:reference",
    "fusion.weight=1.0",  # a fixed weight: eq. 4.4's trust needs more episodes than these runs have
    "human.lr=0.005",
    "human.replay_every=2",
    "trainer.frequency=1.0",
    "trainer.timing.enabled=false",
)
SHORT = "domain.max_episode_steps=100"  # evaluation episodes end sooner: the fused tests stay fast


def _same(a: Any, b: Any) -> bool:
    """Whether two saved states are equal, tensor for tensor (NaN equal to NaN: a replay buffer's storage
    holds uninitialised entries beyond those written)."""
    if isinstance(a, torch.Tensor):
        return (
            isinstance(b, torch.Tensor) and a.dtype == b.dtype and bool(torch.isclose(a, b, 0, 0, True).all())
        )
    if isinstance(a, Mapping):
        return isinstance(b, Mapping) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return isinstance(b, (list, tuple)) and len(a) == len(b) and all(map(_same, a, b))
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    return a == b


def _random_return(episodes: int = 16) -> float:
    return evaluate_gym(compose_config("evaluate", "domain=gym", "policy=random", f"episodes={episodes}"))[
        "mean"
    ]


def test_ppo_alone_on_cartpole_beats_random_and_plays_back(run_learner, tmp_path, one_thread) -> None:
    learner, final = run_learner(
        tmp_path, *CARTPOLE, *TINY, SHORT, "agent.frames=2048", "agent.eval_every=1024"
    )
    random = _random_return()
    assert 15.0 < random < 30.0  # uniformly random actions: about 22
    curve = [r["eval/greedy_return_mean"] for r in learner.history]
    assert [r["frames"] for r in learner.history] == [0, 1024, 2048]
    assert final["eval/greedy_return_mean"] > 2 * random and curve[-1] > curve[0]
    assert learner.ppo.updates == 4 * 16  # epochs x batches of 4 x 32 frames, one minibatch of 128 each
    played = evaluate_gym(compose_config("evaluate", "domain=gym", f"policy={tmp_path}", "episodes=8"))
    assert played["plays"] == "PPO (greedy), logits alone" and played["mean"] > 2 * random


@pytest.mark.parametrize(
    "fusion", ["linear", "annealed", "action_biasing", "control_sharing", "reward_shaping", "none"]
)
def test_every_scheme_ppo_takes_fuses_the_oracles_h_into_a_run(
    fusion, run_learner, tmp_path, one_thread
) -> None:
    """Decision-level rules act on the logits the actions are sampled from; reward shaping on the reward GAE
    reads (r + w H^ of the action taken), the env's own kept beside it."""
    batches = []

    def spy(learner) -> None:
        update = learner.ppo.update
        learner.ppo.update = lambda batch: batches.append(batch.clone()) or update(batch)

    learner, final = run_learner(
        tmp_path,
        *CARTPOLE,
        *TINY,
        *TAUGHT,
        SHORT,
        f"fusion={fusion}",
        "agent.frames=128",
        "agent.eval_every=128",
        prepare=spy,
    )
    assert final["frames"] == 128 and learner.events > 100 and learner.human.applied == learner.events
    if fusion != "none":  # fusion=none has no weight (nothing is fused)
        annealed = fusion == "annealed"  # 1.0 * 0.98 per episode
        assert (final["fusion/weight_mean"] < 1.0) if annealed else (final["fusion/weight_mean"] == 1.0)
    batch = torch.cat(batches)
    nxt = batch["next"]
    shaped = nxt["env_reward"] + batch["human_reward_estimate"].to(nxt["env_reward"].dtype)
    torch.testing.assert_close(nxt["reward"], shaped if fusion == "reward_shaping" else nxt["env_reward"])
    logits, h, fused = batch["env_values"], batch["human_values"], batch["fused_values"]
    if fusion in ("linear", "annealed", "action_biasing"):
        w = batch["fusion_weight"].unsqueeze(-1)  # each decision's weight (annealed: 0.98 per episode)
        torch.testing.assert_close(fused, logits.double() + w * h)
    elif fusion in ("none", "reward_shaping"):
        torch.testing.assert_close(fused, logits)
    policy = learner.checkpoint()["policy"]
    assert policy["kind"] == "gym_ppo" and policy["fusion"]["scheme"] == learner.fusion.decision


def test_fused_ppo_beats_random_resumes_and_plays_back(run_learner, tmp_path, one_thread) -> None:
    """Fused with the oracle, stopped after two points as Ctrl-C stops it, and resumed: the resumed run
    starts from exactly the saved state, two resumes of one checkpoint are the same run, and evaluate.py plays
    what it saved."""
    taught = (*CARTPOLE, *TINY, *TAUGHT, SHORT, "fusion=linear")
    budget = ("agent.frames=512", "agent.eval_every=256")
    _, stopped = run_learner(tmp_path / "a", *taught, *budget, stop_after=2)
    assert stopped is None
    shutil.copytree(tmp_path / "a", tmp_path / "b")
    saved = load_checkpoint(tmp_path / "a")
    resumed = {}

    def same_as_saved(learner) -> None:  # before it learns: the state the checkpoint holds, exactly
        state = learner.checkpoint()["state"]
        for part in ("ppo", "fusion", "human", "rng"):
            assert _same(state[part], saved["state"][part]), part
        assert state["frames"] == 256

    for run in ("a", "b"):
        checkpoint = load_checkpoint(tmp_path / run)
        resumed[run] = run_learner(
            tmp_path / run, *taught, *budget, checkpoint=checkpoint, prepare=same_as_saved
        )
    (la, fa), (lb, fb) = resumed["a"], resumed["b"]
    assert la.resumed and [r["frames"] for r in la.history] == [0, 256, 512]
    assert _same(la.history[:2], saved["history"])
    assert _same(
        {k: v for k, v in fa.items() if k != "wall_s"}, {k: v for k, v in fb.items() if k != "wall_s"}
    )
    for x, y in zip(la.ppo.actor_net.parameters(), lb.ppo.actor_net.parameters(), strict=True):
        assert torch.equal(x, y)
    random = _random_return()
    assert fa["eval/greedy_return_mean"] > 2 * random
    played = evaluate_gym(compose_config("evaluate", "domain=gym", f"policy={tmp_path / 'a'}", "episodes=8"))
    assert played["plays"] == "PPO (greedy), logits fused with H^ (linear)" and played["mean"] > 2 * random


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (("domain.env_id=Pendulum-v1",), "continuous action space"),
        (
            ("fusion=exponential", "trainer.reference=examples.cartpole:reference"),
            "fusion='exponential' with agent=ppo is invalid",
        ),
        (
            ("fusion=human_only", "trainer.reference=examples.cartpole:reference"),
            "agent=dqn fusion=human_only",
        ),
        (
            ("fusion=linear", "fusion.normalise=true", "trainer.reference=examples.cartpole:reference"),
            "allowed: null, false, spread",
        ),
        (("fusion=linear", "trainer=none"), "choose a trainer: oracle"),
        (("fusion=linear", "trainer=oracle"), "needs trainer.reference="),
        (("agent.minibatch_size=1000",), "agent.minibatch_size=1000 is invalid"),
        (("agent.clip_epsilon=0",), "agent.clip_epsilon=0 is invalid"),
    ],
)
def test_bad_input_is_one_line_before_the_run(compose_train, overrides, message) -> None:
    with pytest.raises(ConfigError) as err:
        compose_train(*CARTPOLE, *overrides)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_ppo_on_another_domain_says_where_it_learns(compose_train) -> None:
    with pytest.raises(ConfigError, match="agent=ppo learns gym"):
        compose_train("domain=tetris", "agent=ppo")


def test_cfg_job_composes_ppo_on_gym() -> None:
    out = run_script(
        "train.py",
        "--cfg",
        "job",
        "--resolve",
        *CARTPOLE,
        "fusion=linear",
        "trainer.reference=examples.cartpole:reference",
        timeout=300,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    for text in ("name: ppo", "clip_epsilon: 0.2", "name: oracle", "reference: examples.cartpole:reference"):
        assert text in out.stdout, text
