"""The trust factor: eq. 4.3 from reference policies, eq. 4.4 per episode with every edge case worked by
hand, checkpoint state, and the match rate that feeds both."""

from __future__ import annotations

import json
import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.trust import IncrementalTrust, MatchCounter, trust_from_policies

# ---------------------------------------------------------------- eq. 4.3


def test_trust_from_policies_by_hand():
    lines = torch.tensor([100.0, 80.0, 60.0, 40.0, 20.0], dtype=torch.float64)
    m = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.5], dtype=torch.float64)
    # (90 + 64 + 42 + 24 + 10) / 300
    assert trust_from_policies(lines, m) == pytest.approx(230.0 / 300.0, abs=1e-12)


def test_trust_from_policies_zero_lines_is_mean_match_rate():
    m = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.5], dtype=torch.float64)
    assert trust_from_policies(torch.zeros(5), m) == pytest.approx(0.7, abs=1e-12)
    # one policy with lines: the others carry no weight
    assert trust_from_policies(torch.tensor([0.0, 10.0, 0.0, 0.0, 0.0]), m) == pytest.approx(0.8, abs=1e-12)


@pytest.mark.parametrize(
    ("lines", "m", "match"),
    [
        ([1.0, 2.0], [0.5], "same length"),
        ([], [], "same length"),
        ([-1.0, 2.0], [0.5, 0.5], "lines"),
        ([math.nan, 2.0], [0.5, 0.5], "lines"),
        ([1.0, 2.0], [0.5, 1.5], "match_rates"),
    ],
)
def test_trust_from_policies_rejects_bad_input(lines, m, match):
    with pytest.raises(ValueError, match=match):
        trust_from_policies(torch.tensor(lines), torch.tensor(m))


@settings(max_examples=50, deadline=None, derandomize=True)
@given(
    pairs=st.lists(st.tuples(st.floats(0.0, 1e4), st.floats(0.0, 1.0)), min_size=1, max_size=8),
)
def test_trust_from_policies_lies_between_the_match_rates(pairs):
    lines = torch.tensor([p[0] for p in pairs], dtype=torch.float64)
    m = torch.tensor([p[1] for p in pairs], dtype=torch.float64)
    t = trust_from_policies(lines, m)
    assert float(m.min()) - 1e-12 <= t <= float(m.max()) + 1e-12


# ---------------------------------------------------------------- eq. 4.4


def test_incremental_trust_hand_computed_sequence():
    tr = IncrementalTrust(0.5)
    # first episode: l1 := l2 = 10 -> (10 * .5 + 10 * .8) / 20
    assert tr.update(10, 0.8) == pytest.approx(0.65, abs=1e-12)
    # l1 = 10, l2 = 30: (10 * .65 + 30 * .4) / 40
    assert tr.update(30, 0.4) == pytest.approx(0.4625, abs=1e-12)
    # l2 = 0: the match rate carries no weight, trust unchanged
    assert tr.update(0, 0.9) == pytest.approx(0.4625, abs=1e-12)
    # l1 + l2 = 0: kept
    assert tr.update(0, 0.9) == pytest.approx(0.4625, abs=1e-12)
    # match rate undefined: kept, but the episode's 20 lines become the next l1
    assert tr.update(20, None) == pytest.approx(0.4625, abs=1e-12)
    # l1 = 20, l2 = 5: (20 * .4625 + 5 * 1) / 25
    assert tr.update(5, 1.0) == pytest.approx(0.57, abs=1e-12)
    assert tr.value == tr.trust and tr.episodes == 6 and tr.previous_performance == 5.0


def test_incremental_trust_first_episodes_without_lines():
    tr = IncrementalTrust(0.3)
    assert tr.update(0, 0.9) == 0.3  # l1 = l2 = 0
    # l1 = 0, l2 = 10: the trust becomes the match rate
    assert tr.update(10, 0.5) == pytest.approx(0.5, abs=1e-12)


def test_incremental_trust_first_episode_without_match_rate():
    tr = IncrementalTrust(0.3)
    assert tr.update(12, None) == 0.3
    assert tr.previous_performance == 12.0
    # l1 = 12, l2 = 4: (12 * .3 + 4 * 1) / 16
    assert tr.update(4, 1.0) == pytest.approx(7.6 / 16, abs=1e-12)


def test_incremental_trust_keepaway_hold_times():
    tr = IncrementalTrust(1.0)
    assert tr.update(6.5, 0.0) == pytest.approx(0.5, abs=1e-12)
    assert tr.update(13.0, 0.25) == pytest.approx((6.5 * 0.5 + 13.0 * 0.25) / 19.5, abs=1e-12)


@pytest.mark.parametrize(
    ("perf", "m", "match"),
    [
        (-1.0, 0.5, "performance"),
        (math.inf, 0.5, "performance"),
        (3.0, 1.2, "match_rate"),
        (3.0, math.nan, "match"),
    ],
)
def test_incremental_trust_rejects_bad_updates(perf, m, match):
    tr = IncrementalTrust(0.5)
    with pytest.raises(ValueError, match=match):
        tr.update(perf, m)
    assert tr.episodes == 0 and tr.trust == 0.5


def test_incremental_trust_rejects_bad_initial():
    for bad in (math.nan, -0.1):
        with pytest.raises(ValueError, match="initial"):
            IncrementalTrust(bad)


def test_state_dict_round_trip_continues_identically():
    seq = [(10, 0.8), (30, 0.4), (0, None), (7, 0.6), (12, 0.9)]
    straight = IncrementalTrust(0.5)
    for perf, m in seq:
        straight.update(perf, m)
    first = IncrementalTrust(0.5)
    for perf, m in seq[:2]:
        first.update(perf, m)
    state = json.loads(json.dumps(first.state_dict()))
    assert all(v is None or type(v) in (float, int) for v in state.values())
    resumed = IncrementalTrust(0.0)
    resumed.load_state_dict(state)
    for perf, m in seq[2:]:
        resumed.update(perf, m)
    assert resumed.state_dict() == straight.state_dict()
    fresh = IncrementalTrust(0.2)
    fresh.load_state_dict(IncrementalTrust(0.9).state_dict())
    assert fresh.previous_performance is None and fresh.trust == 0.9


@pytest.mark.parametrize(
    "state",
    [
        {"trust": 0.5},
        {"trust": "x", "previous_performance": None, "episodes": 0},
        {"trust": -1.0, "previous_performance": None, "episodes": 0},
        {"trust": 0.5, "previous_performance": -3.0, "episodes": 0},
        {"trust": 0.5, "previous_performance": None, "episodes": -1},
    ],
)
def test_load_bad_state_raises_checkpoint_error(state):
    tr = IncrementalTrust(0.5)
    with pytest.raises(CheckpointError, match="IncrementalTrust"):
        tr.load_state_dict(state)
    assert tr.trust == 0.5


@settings(max_examples=50, deadline=None, derandomize=True)
@given(
    initial=st.floats(0.0, 1.0),
    episodes=st.lists(
        st.tuples(st.floats(0.0, 500.0), st.one_of(st.none(), st.floats(0.0, 1.0))), min_size=1, max_size=15
    ),
)
def test_incremental_trust_stays_in_unit_interval(initial, episodes):
    tr = IncrementalTrust(initial)
    for perf, m in episodes:
        before = tr.trust
        after = tr.update(perf, m)
        assert -1e-12 <= after <= 1.0 + 1e-12
        if m is None:
            assert after == before
        else:
            assert min(before, m) - 1e-12 <= after <= max(before, m) + 1e-12


# ---------------------------------------------------------------- match rate


def _values(*rows: list[float]) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


def test_match_counter_counts_per_learner_accumulates_and_resets():
    mc = MatchCounter(2)
    assert torch.isnan(mc.rates()).all()
    r = _values([1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 1.0])
    h = _values([5.0, 1.0, 1.0], [3.0, 0.0, 0.0], [0.0, 0.0, 2.0])  # best H^: 0, 0, 2; best R: 0, 1, 2
    mc.count(r, h, torch.ones(3, 3, dtype=torch.bool), torch.tensor([0, 1, 1]))
    assert mc.matches.tolist() == [1, 1] and mc.compared.tolist() == [1, 2]
    assert mc.rates().tolist() == pytest.approx([1.0, 0.5])
    mc.reset(torch.tensor([True, False]))
    assert mc.compared.tolist() == [0, 2] and math.isnan(float(mc.rates()[0]))
    mc.reset()
    assert mc.compared.tolist() == [0, 0]


def test_match_counter_counts_only_decisions_where_h_prefers_a_choosable_action():
    mc = MatchCounter(1)
    r = _values([1.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    h = _values([0.0, 0.0, 0.0], [9.0, 1.0, 1.0])  # an untaught H^; a preference only among masked actions
    choosable = torch.tensor([[True, True, True], [False, True, True]])
    mc.count(r, h, choosable, torch.zeros(2, dtype=torch.int64))
    assert mc.compared.tolist() == [0]  # neither decision compares H^ and R
    # the best is the first best among the choosable actions: H^ picks 1, R picks 1 (row 2 of R masked at 0)
    mc.count(
        _values([0.0, 2.0, 1.0]),
        _values([0.0, 5.0, 1.0]),
        torch.tensor([[False, True, True]]),
        torch.tensor([0]),
    )
    assert (mc.matches.tolist(), mc.compared.tolist()) == ([1], [1])


def test_match_counter_adds_counts_made_elsewhere_and_round_trips():
    mc = MatchCounter(3)
    mc.add(torch.tensor([0, 2, 2]), torch.tensor([1, 2, 0]), torch.tensor([4, 3, 1]))
    assert mc.rates().tolist()[0] == pytest.approx(0.25) and mc.rates().tolist()[2] == pytest.approx(0.5)
    fresh = MatchCounter(3)
    fresh.load_state_dict(mc.state_dict())
    assert torch.equal(fresh.matches, mc.matches) and torch.equal(fresh.compared, mc.compared)
    with pytest.raises(CheckpointError, match="3"):
        MatchCounter(2).load_state_dict(mc.state_dict())


def test_match_rate_feeds_incremental_trust():
    mc, tr = MatchCounter(1), IncrementalTrust(0.5)
    rate = float(mc.rates()[0])
    assert tr.update(8, None if math.isnan(rate) else rate) == 0.5
    mc.add(torch.zeros(1, dtype=torch.int64), torch.tensor([3]), torch.tensor([4]))
    # l1 = 8, l2 = 8: (8 * .5 + 8 * .75) / 16
    assert tr.update(8, float(mc.rates()[0])) == pytest.approx(0.625, abs=1e-12)
