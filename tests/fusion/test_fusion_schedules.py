"""Weight schedules: constant, Knox & Stone's annealed baseline by hand, the trust factor following eq. 4.4
on a hand-computed sequence, the batched shape rule and checkpoint state."""

from __future__ import annotations

import json
import math

import pytest
import torch

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion import AnnealedWeight, ConstantWeight, TrustWeight, as_schedule
from hfrl_torch.fusion.trust import IncrementalTrust, MatchCounter


def test_constant_weight_is_the_same_at_every_episode():
    s = ConstantWeight(0.7)
    assert s.value(0).item() == pytest.approx(0.7)
    assert s.value(123).item() == pytest.approx(0.7)
    assert torch.equal(s.value(torch.tensor([0, 5, 9])), torch.full((3,), 0.7, dtype=torch.float64))


def test_constant_weight_per_learner_lays_learners_along_the_first_dimension():
    s = ConstantWeight([0.0, 1.0, 2.0])
    assert s.value().tolist() == [0.0, 1.0, 2.0]
    assert s.value(7).tolist() == [0.0, 1.0, 2.0]
    rollout = s.value(torch.zeros(3, 4, dtype=torch.int64))
    assert rollout.shape == (3, 4)
    assert rollout[:, 0].tolist() == [0.0, 1.0, 2.0] and rollout[:, 3].tolist() == [0.0, 1.0, 2.0]
    with pytest.raises(ValueError, match="first dimension must be 3"):
        s.value(torch.zeros(4, dtype=torch.int64))


def test_annealed_weight_by_hand():
    s = AnnealedWeight(2.0)
    for k in range(6):
        assert s.value(k).item() == pytest.approx(2.0 * 0.98**k, rel=1e-12)
    assert s.value(torch.tensor([0, 1, 10])).tolist() == pytest.approx([2.0, 1.96, 2.0 * 0.98**10], rel=1e-12)


def test_annealed_weight_own_count_advances_per_learner_at_episode_ends():
    s = AnnealedWeight([1.0, 4.0], factor=0.5)
    assert s.value().tolist() == [1.0, 4.0]
    s.end_episode()
    s.end_episode(ended=torch.tensor([False, True]))
    s.end_episode(ended=torch.tensor([False, True]))
    assert s.episodes.tolist() == [1, 3]
    assert s.value().tolist() == [0.5, 0.5]


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: ConstantWeight(-1.0), ">= 0"),
        (lambda: ConstantWeight(math.nan), "finite"),
        (lambda: ConstantWeight([]), "non-empty"),
        (lambda: AnnealedWeight(1.0, factor=0.0), "factor"),
        (lambda: AnnealedWeight(1.0, factor=1.5), "factor"),
        (lambda: TrustWeight([]), "IncrementalTrust"),
    ],
)
def test_schedules_reject_bad_parameters(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_value_rejects_negative_or_fractional_episodes():
    s = AnnealedWeight(1.0)
    with pytest.raises(ValueError, match=">= 0"):
        s.value(-1)
    with pytest.raises(ValueError, match="integer"):
        s.value(torch.tensor([0.5]))


def test_trust_weight_follows_incremental_trust_by_hand():
    trust = IncrementalTrust(0.5)
    s = TrustWeight(trust)
    # first update: l1 = l2, (0.5 + 0.8) / 2
    s.end_episode(10.0, 0.8)
    assert s.value(1).item() == pytest.approx(0.65, abs=1e-12)
    # (10 * 0.65 + 20 * 0.2) / 30
    s.end_episode(20.0, 0.2)
    assert s.value(2).item() == pytest.approx(10.5 / 30.0, abs=1e-12)
    # no decisions compared: kept; l1 + l2 = 0: kept
    s.end_episode(0.0, None)
    s.end_episode(0.0, 0.9)
    assert s.value().item() == pytest.approx(0.35, abs=1e-12)
    # l1 = 0, l2 = 5: all weight on this episode's match rate
    s.end_episode(5.0, 1.0)
    assert s.value().item() == pytest.approx(1.0, abs=1e-12)
    assert trust.value == pytest.approx(1.0, abs=1e-12)  # the object passed in is held, not copied
    assert trust.episodes == 5


def test_trust_weight_batched_learners_update_independently():
    s = TrustWeight.from_initial([0.5, 0.2, 0.9], learners=3)
    counts = MatchCounter(3)
    counts.add(torch.tensor([0, 1]), torch.tensor([2, 1]), torch.tensor([4, 1]))  # 0.5, 1.0, none
    s.end_episode(torch.tensor([4.0, 2.0, 7.0]), counts.rates(), ended=torch.tensor([True, True, False]))
    assert s.value().tolist() == pytest.approx([0.5, 0.6, 0.9], abs=1e-12)
    # NaN in a tensor of match rates means no decision compared
    s.end_episode([4.0, 6.0, 3.0], torch.tensor([0.0, math.nan, 0.3], dtype=torch.float64))
    # learner 0: (4 * 0.5 + 4 * 0) / 8; learner 1 kept; learner 2 first update: (0.9 + 0.3) / 2
    assert s.value().tolist() == pytest.approx([0.25, 0.6, 0.6], abs=1e-12)
    assert s.episodes.tolist() == [2, 2, 1]


def test_trust_weight_needs_performance_and_one_entry_per_learner():
    s = TrustWeight.from_initial(0.5, learners=2)
    with pytest.raises(ValueError, match="performance"):
        s.end_episode(None, 0.5)
    with pytest.raises(ValueError, match="one per learner"):
        s.end_episode([1.0, 2.0, 3.0], 0.5)


@pytest.mark.parametrize(
    "make",
    [
        lambda: ConstantWeight([0.1, 0.2]),
        lambda: AnnealedWeight([1.0, 3.0], factor=0.9),
        lambda: TrustWeight.from_initial([0.3, 0.6], learners=2),
    ],
)
def test_state_dict_is_plain_json_and_round_trips(make):
    s = make()
    s.end_episode([3.0, 1.0], [0.5, None], ended=torch.tensor([True, False]))
    s.end_episode([2.0, 2.0], [1.0, 0.0])
    state = json.loads(json.dumps(s.state_dict()))
    fresh = make()
    fresh.load_state_dict(state)
    assert torch.equal(fresh.value(), s.value())
    assert fresh.episodes.tolist() == [2, 1]
    fresh.end_episode([1.0, 1.0], [0.2, 0.2])
    s.end_episode([1.0, 1.0], [0.2, 0.2])
    assert torch.equal(fresh.value(), s.value())


def test_load_state_dict_rejects_foreign_or_malformed_state():
    s = AnnealedWeight(1.0)
    with pytest.raises(CheckpointError, match="constant"):
        s.load_state_dict(ConstantWeight(1.0).state_dict())
    with pytest.raises(CheckpointError, match="episodes"):
        s.load_state_dict({"kind": "annealed"})
    with pytest.raises(CheckpointError, match="episodes"):
        s.load_state_dict({**s.state_dict(), "episodes": [0, 0]})


def test_as_schedule_wraps_numbers_and_keeps_schedules():
    a = AnnealedWeight(1.0)
    assert as_schedule(a) is a
    assert isinstance(as_schedule(0.3), ConstantWeight)
    assert as_schedule([0.1, 0.2]).learners == 2
