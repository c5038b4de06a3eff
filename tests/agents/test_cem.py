"""Cross-entropy method: the update by hand, improvement on a small board, resumability."""

from __future__ import annotations

import torch

from hfrl_torch.agents.cem import CEMConfig, CrossEntropyMethod
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.envs.tetris.engine_numba import play
from hfrl_torch.envs.tetris.features import BT, feature_size
from hfrl_torch.envs.tetris.rules import TetrisRules


def test_update_keeps_the_elite_and_adds_noise():
    # score = first weight: the elite are the candidates with the largest first weight
    def rollout(weights, seeds):
        n = len(seeds)
        return weights[:, 0].round().long(), torch.ones(n, dtype=torch.long), torch.zeros(n, dtype=torch.bool)

    cfg = CEMConfig(
        population=10, elite_fraction=0.2, initial_variance=4.0, noise="constant", noise_value=0.5
    )
    cem = CrossEntropyMethod(3, cfg, rollout, seed=0)
    gen = torch.Generator().manual_seed(component_seed(0, "cem_candidates", 0))
    cand = 0.0 + 2.0 * torch.randn(10, 3, generator=gen, dtype=torch.float64)
    scores = cand[:, 0].round()
    elite = torch.argsort(scores, descending=True, stable=True)[:2]
    cem.step()
    assert torch.allclose(cem.mean, cand[elite].mean(0))
    assert torch.allclose(cem.variance, cand[elite].var(0, unbiased=False) + 0.5)
    assert cem.iteration == 1


def test_noise_schedules():
    cem = CrossEntropyMethod(2, CEMConfig(noise="decreasing", noise_start=5.0, noise_decay=10.0), None, 0)
    assert [cem.noise(t) for t in (0, 10, 49, 50, 80)] == [5.0, 4.0, 5.0 - 4.9, 0.0, 0.0]
    assert CrossEntropyMethod(2, CEMConfig(noise="none"), None, 0).noise(3) == 0.0
    assert CrossEntropyMethod(2, CEMConfig(noise="constant", noise_value=4.0), None, 0).noise(99) == 4.0


def _rollout(rules):
    def rollout(weights, seeds):
        return play(rules, BT, weights, seeds)

    return rollout


def test_cem_improves_on_a_small_board():
    rules = TetrisRules(10, 8)
    cfg = CEMConfig(population=50, games_per_candidate=5, eval_games=20)
    cem = CrossEntropyMethod(feature_size(BT, 10), cfg, _rollout(rules), seed=3)
    start = cem.evaluate_mean().double().mean()
    for _ in range(10):
        cem.step()
    end = cem.evaluate_mean().double().mean()
    assert start < 1.0  # all-zero weights always take the first placement
    assert end > 10.0 and end > start + 9.0


def test_interrupted_and_resumed_equals_uninterrupted():
    rules = TetrisRules(8, 8)
    cfg = CEMConfig(population=20, games_per_candidate=2, eval_games=5)
    a = CrossEntropyMethod(feature_size(BT, 8), cfg, _rollout(rules), seed=5)
    for _ in range(4):
        a.step()
    b = CrossEntropyMethod(feature_size(BT, 8), cfg, _rollout(rules), seed=5)
    for _ in range(2):
        b.step()
    c = CrossEntropyMethod(feature_size(BT, 8), cfg, _rollout(rules), seed=5)
    c.load_state_dict({k: v.clone() if torch.is_tensor(v) else v for k, v in b.state_dict().items()})
    for _ in range(2):
        c.step()
    assert torch.equal(a.mean, c.mean) and torch.equal(a.variance, c.variance)
    assert torch.equal(a.evaluate_mean(), c.evaluate_mean())
