"""The adaptive weight's estimators on constructed evidence: the bandit rises for a helpful H^, falls for a
harmful one and follows a trainer who leaves; CE's searched weight; checkpoints of both."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion import Fusion, TrustWeight
from hfrl_torch.fusion.bandit import DEFAULT_ARMS, BanditWeight
from hfrl_torch.fusion.paired import PairedWeight
from hfrl_torch.fusion.schedules import SearchedWeight

ARMS = DEFAULT_ARMS  # (0, 1, 16): no H^, an equal say, H^ decides


def play(bandit: BanditWeight, episodes: int, returns, seed: int = 0) -> torch.Tensor:
    """Run ``episodes`` episodes where arm weight w earns ``returns(w, episode)`` times lognormal noise;
    returns the weights played [episodes, L]."""
    g = torch.Generator().manual_seed(seed)
    played = []
    for e in range(episodes):
        w = bandit.value()
        played.append(w.clone())
        noise = torch.exp(0.4 * torch.randn(w.shape, generator=g, dtype=torch.float64))
        bandit.end_episode(performance=returns(w, e) * noise)
    return torch.stack(played)


def helpful(w: torch.Tensor, e: int) -> torch.Tensor:
    return 4.0 + 10.0 * (w / 16.0).sqrt()  # the more H^, the better: 4 s without, 14 s at the top


def harmful(w: torch.Tensor, e: int) -> torch.Tensor:
    return 6.0 - 3.0 * (w / 16.0).sqrt()  # H^ hurts: 6 s without, 3 s at the top


def test_first_episode_trusts_the_teacher() -> None:
    assert BanditWeight(3).value().tolist() == [16.0] * 3


def test_rises_for_a_helpful_h() -> None:
    bandit = BanditWeight(20, ARMS, seed=1)
    played = play(bandit, 60, helpful)
    late = played[30:]
    assert float((late == 16.0).double().mean()) > 0.7
    assert float(late.mean()) > 10.0


def test_falls_for_a_harmful_h() -> None:
    bandit = BanditWeight(20, ARMS, seed=2)
    played = play(bandit, 60, harmful)
    late = played[30:]
    assert float((late == 16.0).double().mean()) < 0.05  # the harmful H^ no longer decides
    assert float(late.mean()) < 1.5  # mostly no H^; an equal say costs little here, so it is tried


def test_follows_a_trainer_who_leaves() -> None:
    """H^ helps for 100 episodes, then Q overtakes it (H^ frozen, Q still learning): the weight goes."""

    def overtaken(w: torch.Tensor, e: int) -> torch.Tensor:
        q_only = 4.0 + 12.0 * min(e / 300.0, 1.0)  # Q alone reaches 16 s by episode 300
        return torch.where(w > 0, 12.0 + 0 * w, torch.full_like(w, q_only)) * (1.0 - 0.02 * (w / 16.0))

    bandit = BanditWeight(20, ARMS, seed=3)
    played = play(bandit, 500, overtaken)
    assert float((played[50:100] > 0).double().mean()) > 0.7  # H^ worth more than Q early
    assert float((played[-100:] == 0).double().mean()) > 0.7  # Q alone once it is better


def test_stationary_discount_keeps_evidence() -> None:
    bandit = BanditWeight(1, (0.0, 1.0), discount=1.0)
    bandit.end_episode(performance=torch.tensor([10.0]))
    bandit.end_episode(performance=torch.tensor([10.0]))
    assert float(bandit.count.sum()) == pytest.approx(2.0)


def test_only_flagged_learners_move() -> None:
    bandit = BanditWeight(3, ARMS, seed=0)
    bandit.end_episode(performance=torch.tensor([1.0, 2.0, 3.0]), ended=torch.tensor([False, True, False]))
    assert bandit.count[[0, 2]].sum() == 0 and bandit.count[1].sum() == pytest.approx(1.0)
    assert bandit.episodes.tolist() == [0, 1, 0]


def test_probabilities_sum_to_one_and_favour_the_better_arm() -> None:
    bandit = BanditWeight(1, (0.0, 1.0), seed=0)
    for _ in range(10):
        bandit.arm[:] = 0
        bandit.end_episode(performance=torch.tensor([3.0]))
        bandit.arm[:] = 1
        bandit.end_episode(performance=torch.tensor([12.0]))
    p = bandit.probabilities()
    assert float(p.sum()) == pytest.approx(1.0)
    assert float(p[0, 1]) > 0.95


def test_resume_continues_the_same_draws() -> None:
    a = BanditWeight(4, ARMS, seed=5)
    play(a, 20, helpful)
    b = BanditWeight(4, ARMS, seed=99)
    b.load_state_dict(a.state_dict())
    assert torch.equal(play(a, 20, helpful, seed=7), play(b, 20, helpful, seed=7))


def test_bad_states_and_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="at least two"):
        BanditWeight(1, (1.0,))
    with pytest.raises(ValueError, match=">= 0"):
        BanditWeight(1, (-1.0, 1.0))
    with pytest.raises(ValueError, match="discount"):
        BanditWeight(1, ARMS, discount=0.0)
    with pytest.raises(ValueError, match="performance"):
        BanditWeight(1, ARMS).end_episode()
    state = BanditWeight(2, ARMS).state_dict()
    with pytest.raises(CheckpointError, match="arms"):
        BanditWeight(2, (0.0, 2.0)).load_state_dict(state)
    with pytest.raises(CheckpointError):
        BanditWeight(3, ARMS).load_state_dict(state)
    with pytest.raises(CheckpointError, match="bandit"):
        BanditWeight(2, ARMS).load_state_dict({**state, "kind": "trust"})


def test_searched_weight_is_set_and_clamped() -> None:
    w = SearchedWeight([0.5, 0.5])
    assert w.value().tolist() == [0.5, 0.5]
    w.set(torch.tensor(-0.3))
    assert w.value().tolist() == [0.0, 0.0]
    w.set(torch.tensor([2.0, 3.0]))
    w.end_episode()
    assert w.value().tolist() == [2.0, 3.0]
    restored = SearchedWeight([0.0, 0.0])
    restored.load_state_dict(w.state_dict())
    assert restored.value().tolist() == [2.0, 3.0]
    with pytest.raises(CheckpointError, match="search"):
        SearchedWeight([0.0, 0.0]).load_state_dict({**w.state_dict(), "kind": "constant"})


# ---------------------------------------------------------------- CE's search of the weight


def search(best_weight, iterations: int = 30, seed: int = 0) -> list[float]:
    """CE over (one value weight, the weight on H^) where a game's lines peak where the weight on H^ is
    ``best_weight(t)`` (clamped at 0, as the fused rollout does); the mean weight on H^ after each step."""
    from hfrl_torch.agents.cem import CEMConfig, CrossEntropyMethod

    state = {"t": 0}

    def rollout(weights: torch.Tensor, seeds: torch.Tensor):
        w = weights[:, -1].clamp(min=0.0)
        lines = 100.0 * torch.exp(-((w - best_weight(state["t"])) ** 2) / 50.0)
        n = weights.shape[0]
        return lines, torch.full((n,), 10), torch.zeros(n, dtype=torch.bool)

    config = CEMConfig(population=50, noise="constant", noise_value=4.0, games_per_candidate=1, eval_games=1)
    cem = CrossEntropyMethod(
        2, config, rollout, seed, mean=torch.tensor([0.0, 0.5]), scale=torch.tensor([1.0, 0.1])
    )
    out = []
    for t in range(iterations):
        state["t"] = t
        cem.step()
        out.append(float(cem.mean[-1].clamp(min=0.0)))
    return out


def test_search_rises_for_a_helpful_h() -> None:
    assert search(lambda t: 3.0)[-1] == pytest.approx(3.0, abs=0.5)


def test_search_falls_for_a_harmful_h() -> None:
    assert search(lambda t: -5.0)[-1] == 0.0  # the best is no H^ at all: the mean goes below 0


def test_search_follows_a_trainer_who_leaves() -> None:
    path = search(lambda t: 3.0 if t < 20 else 0.0, iterations=45)
    assert path[19] > 2.0 and path[-1] < 0.5


def test_search_scale_sets_the_weight_dimension_apart() -> None:
    from hfrl_torch.agents.cem import CEMConfig, CrossEntropyMethod

    cem = CrossEntropyMethod(3, CEMConfig(), lambda w, s: (w[:, 0],), 0, scale=torch.tensor([1.0, 1.0, 0.1]))
    assert cem.variance.tolist() == pytest.approx([100.0, 100.0, 1.0])
    with pytest.raises(ValueError, match="scale"):
        CrossEntropyMethod(2, CEMConfig(), lambda w, s: (w[:, 0],), 0, scale=torch.tensor([1.0, 0.0]))


def test_the_prior_trusts_h_only_while_the_trainer_teaches() -> None:
    """Equal evidence for every arm: the highest weight is favoured while taught, not after."""
    bandit = BanditWeight(1, seed=0)
    for arm in range(3):
        bandit.arm[:] = arm
        bandit.end_episode(performance=torch.tensor([10.0]))
    taught = bandit.probabilities()[0]
    bandit.taught(torch.tensor([False]))
    left = bandit.probabilities()[0]
    assert float(taught[2]) > 0.5 and float(left[2]) < float(taught[2])
    assert float(left.max() - left.min()) < 0.2  # no arm favoured once the evidence alone speaks
    restored = BanditWeight(1, seed=0)
    restored.load_state_dict(bandit.state_dict())
    assert restored.teaching.tolist() == [False]


# ------------------------------------------------------- CE's paired comparison of weights


def compare(paired: PairedWeight, iterations: int, lines_at, seed: int = 0) -> list[float]:
    """``iterations`` comparisons where the test games at weight w score ``lines_at(w, t)`` times the games'
    own luck (shared by every weight: the same games); the weight played after each."""
    g = torch.Generator().manual_seed(seed)
    played = []
    for t in range(iterations):
        luck = torch.exp(0.8 * torch.randn(30, generator=g, dtype=torch.float64))  # one draw per game
        table = torch.stack(
            [lines_at(float(w), t) * luck * (1 + 0.05 * torch.randn(30, generator=g)) for w in paired.arms]
        )
        paired.compare(table)
        played.append(float(paired.value()[0]))
    return played


def test_paired_rises_for_a_helpful_h() -> None:
    assert compare(PairedWeight(1, first=0), 5, lambda w, t: 20.0 + 30.0 * w)[-1] == 1.0


def test_paired_falls_for_a_harmful_h() -> None:
    assert compare(PairedWeight(1), 5, lambda w, t: 40.0 - 30.0 * w)[-1] == 0.0


def test_paired_follows_a_trainer_who_leaves() -> None:
    """H^ helps while R is young; R alone is best once it has learned: the weight goes to 0."""
    played = compare(PairedWeight(1), 20, lambda w, t: 20.0 + 30.0 * w if t < 8 else 200.0 - 60.0 * w)
    assert played[7] == 1.0 and played[-1] == 0.0


def test_paired_state_round_trips() -> None:
    a = PairedWeight(1)
    compare(a, 3, lambda w, t: 10.0 + w)
    b = PairedWeight(1)
    b.load_state_dict(a.state_dict())
    assert torch.equal(a.scores, b.scores) and a.value().tolist() == b.value().tolist()
    with pytest.raises(CheckpointError, match="arms"):
        PairedWeight(1, (0.0, 2.0)).load_state_dict(a.state_dict())
    with pytest.raises(ValueError, match="discount"):
        PairedWeight(1, discount=1.0)


def test_the_learners_evidence_reaches_the_weight_through_the_fusion():
    """CE never touches its schedule: its comparison and its search arrive through ``Fusion.end_episode``."""
    paired = Fusion.from_option("linear", PairedWeight(1, [0.0, 0.25, 1.0], discount=0.0))
    assert paired.compared_weights().tolist() == [0.0, 0.25, 1.0] and not paired.searches_weight
    assert paired.weight().tolist() == [1.0] and not paired.weight_informed()  # the first arm: no evidence
    games = torch.tensor([[[5.0, 5.0], [30.0, 40.0], [1.0, 2.0]]])  # [L, K, G]: the middle arm won
    paired.end_episode(performance=10.0, compared=games)
    assert paired.weight().tolist() == [0.25] and paired.weight_informed()
    paired.end_episode(performance=10.0)  # no comparison this time: the arm is kept
    assert paired.weight().tolist() == [0.25]
    searched = Fusion.from_option("linear", SearchedWeight(0.5))
    assert searched.searches_weight and searched.compared_weights() is None and searched.weight_informed()
    searched.end_episode(performance=10.0, searched=torch.tensor([1.75]))
    assert searched.weight().tolist() == [1.75]
    trust = Fusion.from_option("linear", TrustWeight.from_initial(0.5))
    assert trust.compared_weights() is None and not trust.searches_weight
