"""Decision-level fusion: every scheme's values and choices on hand-made R and H^ (ties, masks, game-ending
placements), control sharing's rate with a seeded generator, weights from schedules, the SCHEMES list."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.fusion import (
    DECISION_SCHEMES,
    REWARD_SCHEMES,
    SCHEMES,
    AnnealedWeight,
    ConstantWeight,
    FusedActionSelector,
    fuse_values,
    signed_power,
)

# one board, four actions: R favours 2, H^ favours 3, and action 3 has R = 0
R = torch.tensor([[2.0, 1.0, 4.0, 0.0]])
H = torch.tensor([[1.0, 3.0, -0.5, 8.0]])


def test_schemes_list_names_every_scheme_with_its_levels():
    names = [s.name for s in SCHEMES]
    assert len(names) == len(set(names))
    assert set(names) == {
        "none",
        "human_only",
        "linear",
        "exponential",
        "action_biasing",
        "control_sharing",
        "reward_shaping",
        "q_augmentation",
    }
    assert all(s.levels and set(s.levels) <= {"decision", "reward", "target"} for s in SCHEMES)
    assert set(DECISION_SCHEMES) == {
        "none",
        "human_only",
        "linear",
        "exponential",
        "action_biasing",
        "control_sharing",
    }
    assert set(REWARD_SCHEMES) == {"none", "human_only", "linear", "exponential", "reward_shaping"}


@pytest.mark.parametrize(
    ("scheme", "w", "expected"),
    [
        ("none", 1.0, [2.0, 1.0, 4.0, 0.0]),
        ("human_only", 1.0, [1.0, 3.0, -0.5, 8.0]),
        ("linear", 1.0, [3.0, 4.0, 3.5, 8.0]),
        ("linear", 0.1, [2.1, 1.3, 3.95, 0.8]),
        ("action_biasing", 0.1, [2.1, 1.3, 3.95, 0.8]),
        ("reward_shaping", 0.1, [2.1, 1.3, 3.95, 0.8]),
        ("q_augmentation", 0.1, [2.1, 1.3, 3.95, 0.8]),
        # R (1 + H): 2 * 2, 1 * 4, 4 * 0.5, 0 * 9
        ("exponential", 1.0, [4.0, 4.0, 2.0, 0.0]),
        # R (1 + sign(H) |H|^2): 2 * 2, 1 * 10, 4 * 0.75, 0
        ("exponential", 2.0, [4.0, 10.0, 3.0, 0.0]),
        # R (1 + sign(H) |H|^0.5): 2 * 2, 1 + sqrt 3, 4 (1 - sqrt 0.5), 0
        ("exponential", 0.5, [4.0, 1.0 + math.sqrt(3.0), 4.0 * (1.0 - math.sqrt(0.5)), 0.0]),
    ],
)
def test_fuse_values_by_hand(scheme, w, expected):
    out = fuse_values(R, H, scheme, w)
    assert out.shape == R.shape
    assert out[0].tolist() == pytest.approx(expected, abs=1e-6)


def test_fuse_values_returns_new_tensors():
    for scheme in ("none", "human_only"):
        out = fuse_values(R, H, scheme)
        out.add_(1.0)
    assert R[0].tolist() == [2.0, 1.0, 4.0, 0.0] and H[0].tolist() == [1.0, 3.0, -0.5, 8.0]


def test_signed_power_is_odd_and_defined_everywhere():
    h = torch.tensor([-4.0, -1.0, 0.0, 0.25, 9.0], dtype=torch.float64)
    assert signed_power(h, torch.tensor(0.5, dtype=torch.float64)).tolist() == pytest.approx(
        [-2.0, -1.0, 0.0, 0.5, 3.0]
    )
    assert signed_power(h, torch.tensor(0.0, dtype=torch.float64)).tolist() == [-1.0, -1.0, 0.0, 1.0, 1.0]


def test_exponential_with_negative_r_reverses_h():
    # documented: for R < 0 a larger factor makes the product more negative
    r = torch.tensor([[-1.0, -1.0]])
    h = torch.tensor([[0.0, 1.0]])
    assert fuse_values(r, h, "exponential", 1.0)[0].tolist() == [-1.0, -2.0]


def test_per_board_weights_apply_to_their_own_board():
    r = torch.tensor([[1.0, 0.0], [1.0, 0.0]])
    h = torch.tensor([[0.0, 1.0], [0.0, 1.0]])
    out = fuse_values(r, h, "linear", torch.tensor([0.5, 2.0]))
    assert out.tolist() == [[1.0, 0.5], [1.0, 2.0]]
    with pytest.raises(ValueError, match="does not fit"):
        fuse_values(r, h, "linear", torch.tensor([0.5, 2.0, 1.0]))


@pytest.mark.parametrize(
    ("kwargs", "error", "match"),
    [
        ({"scheme": "bogus"}, ValueError, "allowed"),
        ({"scheme": "control_sharing"}, ValueError, "FusedActionSelector"),
        ({"scheme": "linear", "weight": -1.0}, ValueError, ">= 0"),
        ({"scheme": "linear", "weight": math.inf}, ValueError, "finite"),
        ({"scheme": "linear", "weight": "1"}, TypeError, "number or a tensor"),
    ],
)
def test_fuse_values_rejects_bad_input(kwargs, error, match):
    with pytest.raises(error, match=match):
        fuse_values(R, H, **kwargs)


def test_fuse_values_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="differ in shape"):
        fuse_values(R, H[:, :3], "linear")


@settings(max_examples=40, deadline=None, derandomize=True)
@given(
    r=st.lists(st.floats(-100, 100), min_size=3, max_size=3),
    h=st.lists(st.floats(-100, 100), min_size=3, max_size=3),
    w=st.floats(0, 10),
)
def test_linear_is_r_plus_w_h_and_exponential_at_one_is_r_times_one_plus_h(r, h, w):
    rt = torch.tensor([r], dtype=torch.float64)
    ht = torch.tensor([h], dtype=torch.float64)
    assert torch.allclose(fuse_values(rt, ht, "linear", w), rt + w * ht)
    assert torch.allclose(fuse_values(rt, ht, "exponential", 1.0), rt * (1 + ht))


# ---------------------------------------------------------------- the selector


@pytest.mark.parametrize(
    ("scheme", "w", "action"),
    [
        ("none", 1.0, 2),
        ("human_only", 1.0, 3),
        ("linear", 1.0, 3),
        ("linear", 0.1, 2),
        ("action_biasing", 1.0, 3),
        ("exponential", 1.0, 0),  # tie 4.0 / 4.0 at 0 and 1: the first
        ("exponential", 2.0, 1),
        ("control_sharing", 0.0, 2),  # never follows H^
        ("control_sharing", 1.0, 3),  # always follows H^
        ("control_sharing", 5.0, 3),  # min(beta, 1)
    ],
)
def test_selector_choice_by_hand(scheme, w, action):
    sel = FusedActionSelector(scheme, weight=w)
    assert sel(R, H).tolist() == [action]


def test_selector_respects_masks_and_avoids_game_ending_placements():
    mask = torch.tensor([[False, True, True, True]])
    terminal = torch.tensor([[False, False, False, True]])
    # linear, w = 1: [3, 4, 3.5, 8]; 3 ends the game, 0 is masked: 1
    assert FusedActionSelector("linear").forward(R, H, mask, terminal).tolist() == [1]
    # every valid placement ends the game: the best of them
    assert FusedActionSelector("linear").forward(R, H, mask, torch.ones_like(mask)).tolist() == [3]
    # masked-out best: human_only falls back to H^'s best valid placement
    assert FusedActionSelector("human_only").forward(R, H, mask & ~terminal).tolist() == [1]
    # control sharing applies the same rule to whichever argmax it follows
    assert FusedActionSelector("control_sharing", 1.0).forward(R, H, mask, terminal).tolist() == [1]
    mask_env = torch.tensor([[True, True, False, True]])
    assert FusedActionSelector("control_sharing", 0.0).forward(R, H, mask_env, terminal).tolist() == [0]


def test_selector_ties_take_the_first_index_on_every_board():
    r = torch.tensor([[1.0, 1.0, 1.0], [0.0, 2.0, 2.0]])
    h = torch.zeros(2, 3)
    for scheme in ("none", "linear", "exponential", "action_biasing"):
        assert FusedActionSelector(scheme).forward(r, h).tolist() == [0, 1]


def test_selector_rejects_reward_only_schemes():
    with pytest.raises(ValueError, match="allowed"):
        FusedActionSelector("reward_shaping")


def test_selector_weight_from_an_annealed_schedule():
    # linear: [2 + w, 1 + 3w, 4 - 0.5w, 8w]; w = 1 at episode 0 picks 3, w = 1/16 at episode 4 picks 2
    sel = FusedActionSelector("linear", AnnealedWeight(1.0, factor=0.5))
    assert sel(R, H, episode=0).tolist() == [3]
    assert sel(R, H, episode=4).tolist() == [2]
    for _ in range(4):
        sel.schedule.end_episode()
    assert sel(R, H).tolist() == [2]


def test_control_sharing_rate_per_board_matches_min_beta_one():
    """Boards follow H^ independently with probability min(beta, 1).

    Each weight gets n = 10,000 boards; the observed rate's standard deviation is sqrt(p (1 - p) / n) <=
    0.005, and 5 of them bound a false failure by ~6e-7 for any seed (the seed makes the run repeatable).
    """
    betas = torch.tensor([0.1, 0.3, 0.5, 0.9], dtype=torch.float64)
    n = 10_000
    b = n * len(betas)
    r = torch.tensor([[1.0, 0.0]]).expand(b, 2)
    h = torch.tensor([[0.0, 1.0]]).expand(b, 2)
    sel = FusedActionSelector(
        "control_sharing", ConstantWeight(betas.repeat(n)), torch.Generator().manual_seed(7)
    )
    followed = sel(r, h).reshape(n, len(betas)).to(torch.float64)
    assert torch.equal(sel.last_followed_human.reshape(n, len(betas)).to(torch.float64), followed)
    for p, rate in zip(betas.tolist(), followed.mean(0).tolist(), strict=True):
        assert abs(rate - p) <= 5 * math.sqrt(p * (1 - p) / n)
    # a second call draws fresh numbers: the choices are not a copy of the first call's
    again = sel(r, h).reshape(n, len(betas)).to(torch.float64)
    assert not torch.equal(again, followed)
    assert (again.mean(0) - betas).abs().max() < 0.03


def test_control_sharing_is_repeatable_with_the_same_seed_and_state():
    r = torch.tensor([[1.0, 0.0]]).expand(64, 2)
    h = torch.tensor([[0.0, 1.0]]).expand(64, 2)
    a = FusedActionSelector("control_sharing", 0.5, torch.Generator().manual_seed(3))
    b = FusedActionSelector("control_sharing", 0.5, torch.Generator().manual_seed(3))
    first = [a(r, h) for _ in range(3)]
    assert all(torch.equal(x, b(r, h)) for x in first)
    state = a.state_dict()
    nxt = a(r, h)
    c = FusedActionSelector("control_sharing", 0.5, torch.Generator().manual_seed(99))
    c.load_state_dict(state)
    assert torch.equal(c(r, h), nxt)
