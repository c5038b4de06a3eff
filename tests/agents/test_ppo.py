"""``agents.ppo``: PPO on TorchRL's ``ClipPPOLoss`` and ``GAE``, with H^ fused into its policy's preferences.

The loss replays each stored decision with the H^ and weight it was taken with, so its policy at the first
minibatch is the one that acted: the log-probabilities it computes equal those the collector stored, for
every decision rule (control sharing's coin included)."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.collectors import Collector

from hfrl_torch import keys
from hfrl_torch.agents.ppo import PLAYED_WEIGHT, PPO
from hfrl_torch.envs.gym_task import GymTask, task_spaces
from hfrl_torch.experiment.learners.gym_dqn import gym_env, observation_net
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight
from hfrl_torch.models.mlp import ActionMLP

SPACES = task_spaces(GymTask("CartPole-v1"))


def _ppo(fusion: Fusion | None, **kwargs) -> PPO:
    torch.manual_seed(0)
    actor = observation_net(SPACES, [16], [1.0] * 4)
    critic = ActionMLP(SPACES.observation_size, 1, [16])
    return PPO(actor, critic, keys.OBSERVATION, fusion, seed=1, **kwargs)


def _batch(ppo: PPO, fusion: Fusion | None, frames: int = 64):
    """One collected batch [4, T] of CartPole, H^ a fixed random linear function of the observation."""
    modules = [ppo.actor]
    if fusion is not None:
        h = torch.nn.Linear(4, 2).double()
        human = TensorDictModule(
            lambda obs: h(obs.double()).detach(), in_keys=[keys.OBSERVATION], out_keys=[keys.HUMAN_VALUES]
        )
        modules = [human, ppo.actor]
    collector = Collector(
        gym_env(GymTask("CartPole-v1"), 4, 0),
        TensorDictSequential(*modules),
        frames_per_batch=frames,
        total_frames=-1,
    )
    batch = next(iter(collector))
    collector.shutdown()
    return batch


@pytest.mark.parametrize("rule", ["none", "linear", "control_sharing"])
def test_the_loss_replays_each_decision_as_it_was_taken(rule, one_thread) -> None:
    fusion = Fusion(rule, "none", ConstantWeight(0.5), seed=3)
    ppo = _ppo(fusion)
    batch = _batch(ppo, fusion)
    r, h, fused = batch[keys.ENV_VALUES], batch[keys.HUMAN_VALUES], batch[keys.FUSED_VALUES]
    played = batch[PLAYED_WEIGHT]
    if rule == "linear":
        torch.testing.assert_close(fused, r.double() + 0.5 * h)
        assert bool((played == 0.5).all())
    elif rule == "control_sharing":  # each decision followed H^ or the policy, by the fusion's coin
        followed = played == 1.0
        assert bool(((played == 0.0) | followed).all()) and 0 < int(followed.sum()) < followed.numel()
        torch.testing.assert_close(fused, torch.where(followed.unsqueeze(-1), h, r.double()))
    else:
        torch.testing.assert_close(fused, r)
    stored = batch["action_log_prob"]
    fusion.eval(True)
    dist = ppo.loss.actor_network.get_dist(batch.clone())
    torch.testing.assert_close(dist.log_prob(batch[keys.ACTION]).to(stored.dtype), stored)


def test_an_update_moves_the_acting_policy_and_keeps_the_fusions_count(one_thread) -> None:
    fusion = Fusion("linear", "none", ConstantWeight(1.0), seed=3)
    ppo = _ppo(fusion, epochs=2, minibatch_size=32)
    batch = _batch(ppo, fusion)
    counted = fusion.matches.state_dict()
    before = [p.detach().clone() for p in ppo.actor_net.parameters()]
    losses = ppo.update(batch)
    assert ppo.updates == 2 * 2 and set(losses) == {"loss", "loss_objective", "loss_critic", "entropy"}
    assert any(not torch.equal(a, p) for a, p in zip(before, ppo.actor_net.parameters(), strict=True))
    assert not fusion.evaluating  # the update replays in evaluation mode, then gives the mode back
    assert str(fusion.matches.state_dict()) == str(counted)  # replaying counts no decision again
    assert {"advantage", "value_target"} <= set(batch.keys())  # GAE, TorchRL's, wrote its estimates


def test_state_dict_round_trips(one_thread) -> None:
    a = _ppo(None)
    a.update(_batch(a, None))
    b = _ppo(None)
    b.load_state_dict(a.state_dict())
    for x, y in zip(a.actor_net.parameters(), b.actor_net.parameters(), strict=True):
        assert torch.equal(x, y)
    assert torch.equal(a.generator.get_state(), b.generator.get_state()) and b.updates == a.updates
