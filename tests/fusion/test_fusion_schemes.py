"""Decision-level fusion through the one component: every scheme's values and choices on hand-made R and H^
(ties, masks, game-ending placements), control sharing's rate with a seeded generator, weights from
schedules, the options table and the SCHEMES list."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.fusion import (
    DECISION_SCHEMES,
    FUSIONS,
    OPTIONS,
    REWARD_SCHEMES,
    SCHEMES,
    AnnealedWeight,
    ConstantWeight,
    Fusion,
    FusionModule,
    as_schedule,
    fuse_values,
    signed_power,
)

# one board, four actions: R favours 2, H^ favours 3, and action 3 has R = 0
R = torch.tensor([[2.0, 1.0, 4.0, 0.0]])
H = torch.tensor([[1.0, 3.0, -0.5, 8.0]])


def _decisions(r, h, mask=None, terminal=None) -> TensorDict:
    td = {keys.ENV_VALUES: r, keys.HUMAN_VALUES: h}
    if mask is not None:
        td[keys.ACTION_MASK] = mask
    if terminal is not None:
        td[keys.AFTERSTATE_TERMINAL] = terminal
    return TensorDict(td, batch_size=[r.shape[0]])


def _fusion(scheme: str, weight=1.0, seed: int = 0, scaling: str = "none") -> Fusion:
    return Fusion(scheme, "none", as_schedule(weight), seed=seed, scaling=scaling)


def choose(scheme, r, h, mask=None, terminal=None, weight=1.0, fusion: Fusion | None = None) -> list[int]:
    """The action of each board chosen through the fusion component's TorchRL face (greedy selection)."""
    module = FusionModule(fusion if fusion is not None else _fusion(scheme, weight), select="greedy")
    return module(_decisions(r, h, mask, terminal)).get(keys.ACTION).tolist()


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
    }
    assert all(s.levels and set(s.levels) <= {"decision", "reward"} for s in SCHEMES)
    assert set(DECISION_SCHEMES) == {
        "none",
        "human_only",
        "linear",
        "exponential",
        "action_biasing",
        "control_sharing",
    }
    assert set(REWARD_SCHEMES) == {"none", "human_only", "linear", "exponential", "reward_shaping"}


def test_every_config_option_names_its_decision_and_reward_rules():
    assert (
        set(FUSIONS)
        == set(OPTIONS)
        == {
            "none",
            "human_only",
            "linear",
            "exponential",
            "annealed",
            "action_biasing",
            "control_sharing",
            "reward_shaping",
        }
    )
    assert all(o.decision in DECISION_SCHEMES and o.reward in REWARD_SCHEMES for o in OPTIONS.values())
    assert OPTIONS["reward_shaping"] == ("none", "reward_shaping")  # shaping acts on the reward only
    assert OPTIONS["annealed"].decision == OPTIONS["action_biasing"].decision == "linear"
    assert {o.reward for k, o in OPTIONS.items() if k != "reward_shaping"} == {"none"}


@pytest.mark.parametrize(
    ("scheme", "w", "expected"),
    [
        ("none", 1.0, [2.0, 1.0, 4.0, 0.0]),
        ("human_only", 1.0, [1.0, 3.0, -0.5, 8.0]),
        ("linear", 1.0, [3.0, 4.0, 3.5, 8.0]),
        ("linear", 0.1, [2.1, 1.3, 3.95, 0.8]),
        ("action_biasing", 0.1, [2.1, 1.3, 3.95, 0.8]),
        ("reward_shaping", 0.1, [2.1, 1.3, 3.95, 0.8]),
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
        ({"scheme": "control_sharing"}, ValueError, "use Fusion"),
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


# ---------------------------------------------------------------- the choice


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
def test_choice_by_hand(scheme, w, action):
    assert choose(scheme, R, H, weight=w) == [action]


def test_choice_respects_masks_and_avoids_game_ending_placements():
    mask = torch.tensor([[False, True, True, True]])
    terminal = torch.tensor([[False, False, False, True]])
    # linear, w = 1: [3, 4, 3.5, 8]; 3 ends the game, 0 is masked: 1
    assert choose("linear", R, H, mask, terminal) == [1]
    # every valid placement ends the game: the best of them
    assert choose("linear", R, H, mask, torch.ones_like(mask)) == [3]
    # masked-out best: human_only falls back to H^'s best valid placement
    assert choose("human_only", R, H, mask & ~terminal) == [1]
    # control sharing applies the same rule to whichever argmax it follows
    assert choose("control_sharing", R, H, mask, terminal, weight=1.0) == [1]
    mask_env = torch.tensor([[True, True, False, True]])
    assert choose("control_sharing", R, H, mask_env, terminal, weight=0.0) == [0]


def test_choice_ties_take_the_first_index_on_every_board():
    r = torch.tensor([[1.0, 1.0, 1.0], [0.0, 2.0, 2.0]])
    h = torch.zeros(2, 3)
    for scheme in ("none", "linear", "exponential", "action_biasing"):
        assert choose(scheme, r, h) == [0, 1]


def test_fusion_rejects_unknown_rules_and_writes_the_weight_it_used():
    with pytest.raises(ValueError, match="allowed"):
        Fusion("reward_shaping", "none", as_schedule(1.0))
    with pytest.raises(ValueError, match="allowed"):
        Fusion.from_option("average", as_schedule(1.0))
    td = _fusion("linear", 0.25).fuse(_decisions(R, H))
    assert td[keys.FUSION_WEIGHT].tolist() == [0.25]
    torch.testing.assert_close(td[keys.FUSED_VALUES], fuse_values(R, H, "linear", 0.25))


def test_weight_from_an_annealed_schedule_follows_the_fusions_episodes():
    # linear: [2 + w, 1 + 3w, 4 - 0.5w, 8w]; w = 1 at episode 0 picks 3, w = 1/16 at episode 4 picks 2
    fusion = Fusion("linear", "none", AnnealedWeight(1.0, factor=0.5))
    assert choose("linear", R, H, fusion=fusion) == [3]
    for _ in range(4):
        fusion.end_episode()
    assert choose("linear", R, H, fusion=fusion) == [2]


def test_weights_per_learner_and_from_a_key():
    r = R.expand(3, 4)
    h = H.expand(3, 4)
    fusion = Fusion("linear", "none", ConstantWeight([1.0, 0.1, 1.0]))
    assert choose("linear", r, h, fusion=fusion) == [3, 2, 3]  # row m is learner m
    td = _decisions(r, h).set(keys.LEARNER, torch.tensor([1, 1, 0]))
    assert FusionModule(fusion, select="greedy")(td)[keys.ACTION].tolist() == [2, 2, 3]
    td = _decisions(r, h).set("my_weight", torch.tensor([0.1, 1.0, 0.1], dtype=torch.float64))
    out = FusionModule(fusion, select="greedy", weight_key="my_weight")(td)
    assert out[keys.ACTION].tolist() == [2, 3, 2]


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
    fusion = Fusion("control_sharing", "none", ConstantWeight(betas.repeat(n)), seed=7)
    followed = torch.tensor(choose("control_sharing", r, h, fusion=fusion)).reshape(n, len(betas)).double()
    assert fusion.followed_human == int(followed.sum())
    for p, rate in zip(betas.tolist(), followed.mean(0).tolist(), strict=True):
        assert abs(rate - p) <= 5 * math.sqrt(p * (1 - p) / n)
    # a second call draws fresh numbers: the choices are not a copy of the first call's
    again = torch.tensor(choose("control_sharing", r, h, fusion=fusion)).reshape(n, len(betas)).double()
    assert not torch.equal(again, followed)
    assert (again.mean(0) - betas).abs().max() < 0.03
    # in evaluation mode it follows H^ exactly where min(w, 1) >= 0.5, the likelier side of its coin
    fusion.eval()
    td = _decisions(r[:4], h[:4]).set(keys.LEARNER, torch.arange(4))
    assert FusionModule(fusion, select="greedy")(td)[keys.ACTION].tolist() == [0, 0, 1, 1]


def test_control_sharing_is_repeatable_with_the_same_seed_and_state():
    r = torch.tensor([[1.0, 0.0]]).expand(64, 2)
    h = torch.tensor([[0.0, 1.0]]).expand(64, 2)
    a, b = _fusion("control_sharing", 0.5, seed=3), _fusion("control_sharing", 0.5, seed=3)
    first = [choose("", r, h, fusion=a) for _ in range(3)]
    assert all(x == choose("", r, h, fusion=b) for x in first)
    state = a.state_dict()
    nxt = choose("", r, h, fusion=a)
    c = _fusion("control_sharing", 0.5, seed=99)
    c.load_state_dict(state)
    assert choose("", r, h, fusion=c) == nxt


def test_scales_decision_and_spread():
    r = torch.tensor([[1000.0, 990.0, 0.0]])  # R prefers action 0 by a little (on its scale)
    h = torch.tensor([[-0.01, 0.01, 0.0]])  # H^ prefers action 1
    assert choose("linear", r, h, weight=0.5) == [0]  # raw: H^ is a rounding error next to R
    assert choose("linear", r, h, fusion=_fusion("linear", 0.5, scaling="decision")) == [1]
    # spread: H^ times the learner's running mean of max R - min R (rate 0.01 from the floor of 1)
    spread = _fusion("linear", 1.0, scaling="spread")
    q, hh = torch.tensor([[10.0, 0.0]]), torch.tensor([[0.0, 1.0]])
    td = spread.fuse(_decisions(q, hh))
    assert spread.q_spread.tolist() == pytest.approx([0.99 * 1.0 + 0.01 * 10.0])
    torch.testing.assert_close(td[keys.FUSED_VALUES], torch.tensor([[10.0, 1.09]], dtype=torch.float64))
    # the exponential rule scales R by a factor of H^ alone: raw values under spread
    expo = _fusion("exponential", 1.0, scaling="spread")
    torch.testing.assert_close(
        expo.fuse(_decisions(q, hh))[keys.FUSED_VALUES], fuse_values(q, hh, "exponential", 1.0)
    )


def test_match_count_goes_through_the_fusion_and_feeds_the_trust():
    from hfrl_torch.fusion import TrustWeight

    fusion = Fusion.from_option("linear", TrustWeight.from_initial(0.5, learners=2))
    r = torch.tensor([[1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    h = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]])  # match, mismatch, H^ prefers nothing
    fusion.fuse(_decisions(r, h).set(keys.LEARNER, torch.tensor([0, 1, 1])))
    assert fusion.matches.matches.tolist() == [1, 0] and fusion.matches.compared.tolist() == [1, 1]
    fusion.end_episode(performance=torch.tensor([4.0, 4.0]))
    # first update: (trust + m) / 2 per learner
    assert fusion.weight().tolist() == pytest.approx([0.75, 0.25])
    assert fusion.matches.compared.tolist() == [0, 0]
    fusion.eval()
    fusion.fuse(_decisions(r, h).set(keys.LEARNER, torch.tensor([0, 1, 1])))
    assert fusion.matches.compared.tolist() == [0, 0]  # evaluation counts nothing


def test_a_learner_explores_around_its_choice_unless_the_fusion_says_not() -> None:
    """``Fusion(explore=False)`` (the Sarsa keepers under a bandit): a choice that weighs H^ is greedy, as
    TAMER's is; a choice on R alone still explores, and TAMER's human-only choice never does."""
    weights = ConstantWeight([0.0, 1.0, 16.0])
    assert Fusion("linear", "none", weights).explores
    assert not Fusion("linear", "none", weights, explore=False).explores
    assert not Fusion("control_sharing", "none", weights, explore=False).explores
    assert Fusion("none", "reward_shaping", weights, explore=False).explores
    assert not Fusion("human_only", "none", weights).explores
