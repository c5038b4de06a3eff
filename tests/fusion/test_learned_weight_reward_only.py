"""The learned weight with reward-level fusion alone: ``FeedbackFusion`` learns a ``BanditWeight`` it owns
from each episode's return, refuses the weights it cannot learn (trust, paired, searched) with one line,
and with ``end_episodes=True`` ends a shared ``Fusion``'s episodes, so a ``FusionModule``'s match count moves
the trust factor in a plain TorchRL rollout on ``GymEnv("CartPole-v1")``."""

from __future__ import annotations

import pytest
import torch
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.envs import GymEnv, SerialEnv, TransformedEnv

from hfrl_torch import keys
from hfrl_torch.fusion import (
    HUMAN_REWARD_ESTIMATE,
    ConstantWeight,
    FeedbackFusion,
    Fusion,
    FusionModule,
    TrustWeight,
)
from hfrl_torch.fusion.bandit import BanditWeight
from hfrl_torch.fusion.paired import PairedWeight
from hfrl_torch.fusion.schedules import SearchedWeight


class _Recorded(ConstantWeight):
    """A constant weight that keeps every ``end_episode`` call's evidence."""

    kind = "recorded"

    def __init__(self, w: float, learners: int = 1) -> None:
        super().__init__([w] * learners)
        self.calls: list[tuple[list[bool], list[float]]] = []

    def end_episode(self, performance=None, match_rate=None, ended=None, **_) -> None:
        flags = torch.ones(self.learners, dtype=torch.bool) if ended is None else ended
        self.calls.append((flags.tolist(), torch.as_tensor(performance).reshape(-1).tolist()))
        super().end_episode(ended=flags)


def _returns(td) -> list[float]:
    """Each finished episode's return of the env reward, in order, from an unbatched rollout."""
    out, total = [], 0.0
    for r, d in zip(td["next", keys.ENV_REWARD].flatten(), td["next", keys.DONE].flatten(), strict=True):
        total += float(r)
        if d:
            out.append(total)
            total = 0.0
    return out


@pytest.mark.parametrize(
    ("schedule", "missing"),
    [
        (TrustWeight.from_initial(0.5), "the match rate of decisions"),
        (PairedWeight(1), "test games the learner plays at several weights"),
        (SearchedWeight(1.0), "the learner's own search"),
    ],
)
def test_weights_learned_from_what_a_transform_never_sees_are_refused(schedule, missing):
    with pytest.raises(
        ValueError, match=f"learns from {missing}.*pass a Fusion shared with the FusionModule"
    ):
        FeedbackFusion("reward_shaping", schedule)


def test_an_owned_bandit_weight_learns_from_each_episodes_return_on_cartpole():
    torch.manual_seed(0)
    bandit = BanditWeight(1, arms=(0.0, 1.0), seed=0)
    fusion = FeedbackFusion("reward_shaping", bandit)
    assert fusion.end_episodes
    env = TransformedEnv(GymEnv("CartPole-v1"), fusion)
    env.set_seed(0)
    td = env.rollout(120, break_when_any_done=False)  # random actions: episodes of ~20 steps
    episodes = int(td["next", keys.DONE].sum())
    assert episodes >= 3
    assert int(bandit.episodes[0]) == episodes == int(fusion.episodes)
    assert float(bandit.count.sum()) > 0  # every episode scored at its arm


def test_a_shared_fusion_with_end_episodes_gets_each_episodes_return():
    schedule = _Recorded(0.5)
    env = TransformedEnv(
        GymEnv("CartPole-v1"), FeedbackFusion(Fusion("none", "linear", schedule), end_episodes=True)
    )
    env.set_seed(1)
    td = env.rollout(100, break_when_any_done=False)
    assert [perf for _, perf in schedule.calls] == [[r] for r in _returns(td)]
    shared = FeedbackFusion(Fusion("none", "linear", _Recorded(0.5)))
    assert not shared.end_episodes  # the loop that shares it ends its episodes


def test_one_learner_per_board_in_a_serial_env():
    schedule = _Recorded(0.5, learners=2)
    fusion = FeedbackFusion(Fusion("none", "linear", schedule), end_episodes=True)
    env = TransformedEnv(SerialEnv(2, lambda: GymEnv("CartPole-v1")), fusion)
    env.set_seed(2)
    td = env.rollout(80, break_when_any_done=False)
    done = td["next", keys.DONE].squeeze(-1)  # [2, T]
    ended = torch.tensor([flags for flags, _ in schedule.calls])
    assert ended.sum(0).tolist() == done.sum(-1).tolist()  # each board's episodes went to its own learner


class _Lean(torch.nn.Module):
    def __init__(self, sign: float) -> None:
        super().__init__()
        self.sign = sign

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        lean = obs[..., 2:3] + obs[..., 3:4]
        return self.sign * torch.cat([-lean, lean], -1)


def test_the_trust_factor_moves_with_reward_level_fusion_in_a_plain_rollout():
    fusion = Fusion("none", "reward_shaping", TrustWeight.from_initial(0.5))
    env = TransformedEnv(GymEnv("CartPole-v1"), FeedbackFusion(fusion, end_episodes=True))
    env.set_seed(3)
    chosen = TensorDictModule(
        lambda h, a: (h * a).sum(-1, keepdim=True),
        in_keys=[keys.HUMAN_VALUES, "action"],
        out_keys=[HUMAN_REWARD_ESTIMATE],
    )
    policy = TensorDictSequential(
        TensorDictModule(_Lean(-1.0), in_keys=["observation"], out_keys=[keys.ENV_VALUES]),
        TensorDictModule(_Lean(-1.0), in_keys=["observation"], out_keys=[keys.HUMAN_VALUES]),
        FusionModule(fusion, "greedy", spec=env.full_action_spec),  # counts argmax R against argmax H^
        chosen,
    )
    env.rollout(60, policy, break_when_any_done=False)
    # R and H^ agree on every decision (both push the pole over: short episodes): m = 1, and eq. 4.4 moves the
    # trust up from 0.5 after each episode
    assert int(fusion.schedule.episodes[0]) >= 1
    assert float(fusion.weight()[0]) > 0.5


def test_learners_that_fit_neither_one_nor_one_per_board_are_refused_at_reset():
    fusion = FeedbackFusion("reward_shaping", BanditWeight(3, arms=(0.0, 1.0)))
    env = TransformedEnv(SerialEnv(2, lambda: GymEnv("CartPole-v1")), fusion)
    with pytest.raises(
        ValueError, match="ends episodes of 3 learners on 2 boards; allowed: one learner, or one"
    ):
        env.reset()
    env.close()
