"""LinearRewardModel: TAMER's update against hand-computed weights, silence, zero credit, learner batches."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.models.reward_model import LinearRewardModel


def _t(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def test_update_matches_hand_computed_weights():
    m = LinearRewardModel(2, learners=1)
    # w = 0: errors are h; w += 0.1 * (1 * 1 * [1, 2] + 0.5 * (-1) * [0, 1]) = [0.1, 0.15]
    err = m.update(_t([[[1.0, 2.0], [0.0, 1.0]]]), _t([[1.0, -1.0]]), _t([[1.0, 0.5]]), alpha=0.1)
    assert torch.allclose(err, _t([[1.0, -1.0]]))
    assert torch.allclose(m.weight, _t([[0.1, 0.15]]))
    # H^([3, -1]) = 0.3 - 0.15 = 0.15; error 0.85; w += 0.1 * 0.85 * [3, -1]
    err = m.update(_t([[[3.0, -1.0]]]), _t([[1.0]]), _t([[1.0]]), alpha=0.1)
    assert err.item() == pytest.approx(0.85)
    assert torch.allclose(m.weight, _t([[0.355, 0.065]]))


def test_all_rows_use_the_weights_before_the_update():
    m = LinearRewardModel(1, learners=1)
    m.weight.fill_(1.0)
    # both rows predict 2.0 from the old weights: errors -1 and +1 cancel, so w stays 1
    m.update(_t([[[2.0], [2.0]]]), _t([[1.0, 3.0]]), _t([[1.0, 1.0]]), alpha=0.5)
    assert m.weight.item() == pytest.approx(1.0)


def test_zero_credit_and_silence_change_nothing():
    m = LinearRewardModel(3, learners=2)
    m.weight.copy_(_t([[0.5, -1.0, 2.0], [1.0, 1.0, 1.0]]))
    before = m.weight.clone()
    phi = torch.randn(2, 4, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    err = m.update(phi, _t([[1.0, -1.0, 1.0, 1.0]] * 2), torch.zeros(2, 4, dtype=torch.float64), alpha=1.0)
    assert torch.equal(m.weight, before) and torch.equal(err, torch.zeros(2, 4, dtype=torch.float64))
    h = _t([[0.0, float("nan"), 0.0, 0.0], [0.0, 0.0, float("nan"), 0.0]])
    err = m.update(phi, h, torch.ones(2, 4, dtype=torch.float64), alpha=1.0)
    assert torch.equal(m.weight, before) and not torch.isnan(err).any()


def test_learners_are_independent():
    g = torch.Generator().manual_seed(1)
    phi = torch.randn(3, 5, 4, generator=g, dtype=torch.float64)
    h = torch.sign(torch.randn(3, 5, generator=g, dtype=torch.float64))
    credit = torch.rand(3, 5, generator=g, dtype=torch.float64)
    credit[0] = 0.0
    batch = LinearRewardModel(4, learners=3)
    batch.update(phi, h, credit, alpha=0.05)
    assert torch.equal(batch.weight[0], torch.zeros(4, dtype=torch.float64))
    for i in (1, 2):
        single = LinearRewardModel(4, learners=1)
        single.update(phi[i : i + 1], h[i : i + 1], credit[i : i + 1], alpha=0.05)
        assert torch.allclose(batch.weight[i], single.weight[0])


def test_forward_shapes_and_values():
    m = LinearRewardModel(2, learners=2)
    m.weight.copy_(_t([[1.0, 0.0], [0.0, 2.0]]))
    phi = torch.ones(2, 3, 5, 2)
    out = m(phi)
    assert out.shape == (2, 3, 5) and out.dtype == torch.float64
    assert torch.all(out[0] == 1.0) and torch.all(out[1] == 2.0)
    with pytest.raises(ValueError, match="phi must be"):
        m(torch.ones(3, 2))
    with pytest.raises(ValueError, match="update needs"):
        m.update(torch.ones(2, 3, 2), torch.ones(2, 4), torch.ones(2, 3), alpha=0.1)
