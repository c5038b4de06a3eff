"""keeper_transitions: the raw turn-taking steps re-laid as each keeper's own SMDP transitions, which a plain
TorchRL DQNLoss takes as they are."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import Categorical
from torchrl.modules import MLP, QValueActor
from torchrl.objectives import DQNLoss

from hfrl_torch import keys
from hfrl_torch.envs.keepaway import TASKS, KeepawayEnv
from hfrl_torch.envs.keepaway.transitions import keeper_transitions

SYNCS = ("all", "any")
STEPS = {"all": 30, "any": 50}  # a step is a decision of every field ("all") or often one cycle ("any")
FIELDS = {"all": 1, "any": 2}


@pytest.fixture(scope="module")
def rollouts() -> dict:
    """One random rollout per sync mode (the simulator's torch path takes seconds)."""
    out = {}
    for sync in SYNCS:
        torch.manual_seed(0)
        env = KeepawayEnv(FIELDS[sync], seed=4, sync=sync, **TASKS["exact"])
        out[sync] = (env, env.rollout(STEPS[sync], break_when_any_done=False))
    return out


@pytest.mark.parametrize("sync", SYNCS)
def test_each_keepers_rewards_add_up_to_its_time_in_play(sync, rollouts):
    _, td = rollouts[sync]
    tr = keeper_transitions(td)
    assert tr.batch_size[0] > 0 and int(tr["next", keys.DONE].sum()) > 0
    live = ~tr["next", keys.DONE].squeeze(-1)
    # a non-terminal transition runs from a keeper's decision to the same keeper's next one
    assert torch.equal(tr[keys.KEEPER][live], tr["next", keys.KEEPER][live])
    gap = (tr["next", keys.EPISODE_CYCLES] - tr[keys.EPISODE_CYCLES])[live].float()
    assert torch.equal(tr["next", keys.REWARD].squeeze(-1)[live], gap)
    # within every complete episode each keeper's rewards sum to the cycles from its first decision to the end
    n = td["next", keys.EPISODE_END_REWARDS].shape[-1]
    checked = 0
    for b in range(td.batch_size[0]):
        first: dict[int, int] = {}
        for t in range(td.batch_size[1]):
            if td[keys.DECIDING][b, t]:
                first.setdefault(int(td[keys.KEEPER][b, t]), int(td[keys.EPISODE_CYCLES][b, t]))
            if td["next", keys.DONE][b, t]:
                end = int(td["next", keys.EPISODE_CYCLES][b, t])
                owed = {k: end - c for k, c in first.items()}
                got = dict.fromkeys(range(n), 0.0)
                for k, c in first.items():  # this episode's transitions: decisions from c on, by field b
                    mine = (tr[keys.KEEPER] == k) & (tr[keys.EPISODE_CYCLES] >= c)
                    mine &= _field_episode(td, tr, b, t)
                    got[k] = float(tr["next", keys.REWARD].squeeze(-1)[mine].sum())
                assert {k: got[k] for k in owed} == pytest.approx(owed)
                checked += 1
                first = {}
    assert checked >= 2


def _field_episode(td, tr, b: int, t: int) -> torch.Tensor:
    """The transitions of field b's episode that ended at step t (found by their decisions' observations)."""
    start = t
    while start > 0 and not td["next", keys.DONE][b, start - 1]:
        start -= 1
    obs = td[keys.OBSERVATION][b, start : t + 1]
    return (tr[keys.OBSERVATION].unsqueeze(1) == obs.unsqueeze(0)).all(-1).any(1)


def test_the_raw_steps_pair_one_keepers_action_with_anothers_reward(rollouts):
    _, td = rollouts["all"]
    nxt_keeper = td["next", keys.KEEPER]
    live = ~td["next", keys.DONE].squeeze(-1)
    assert bool((td[keys.KEEPER][live] != nxt_keeper[live]).any())  # what keeper_transitions re-lays


def test_a_plain_dqn_loss_takes_the_transitions(rollouts):
    env, td = rollouts["all"]
    tr = keeper_transitions(td)
    features, actions = tr[keys.OBSERVATION].shape[-1], env.action_spec.space.n
    actor = QValueActor(
        MLP(in_features=features, out_features=actions, num_cells=[16]),
        in_keys=[keys.OBSERVATION],
        spec=Categorical(actions),
    )
    loss = DQNLoss(actor, action_space="categorical", delay_value=False)
    loss.make_value_estimator(gamma=1.0)
    out = loss(tr.clone())
    assert torch.isfinite(out["loss"])
    out["loss"].backward()
    assert all(p.grad is not None for p in actor.parameters())


def test_no_time_dimension_is_refused(rollouts):
    _, td = rollouts["all"]
    with pytest.raises(ValueError, match="needs a rollout"):
        keeper_transitions(td[:, 0][0])
