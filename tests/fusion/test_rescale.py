"""rescale_range and the fusion's ``scaling="decision"``: R and H^ on a common [0, 1] scale."""

from __future__ import annotations

import torch
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.fusion import Fusion, FusionModule, as_schedule, rescale_range


def test_rescale_maps_the_choosable_range_to_unit_interval():
    v = torch.tensor([[3.0, 1.0, 5.0, 100.0], [2.0, 2.0, 2.0, 2.0]])
    mask = torch.tensor([[True, True, True, False], [True, True, True, True]])
    out = rescale_range(v, mask)
    torch.testing.assert_close(out[0, :3], torch.tensor([0.5, 0.0, 1.0], dtype=torch.float64))
    assert torch.equal(out[1], torch.zeros(4, dtype=torch.float64))  # all equal: no preference


def test_rescale_ignores_game_ending_actions_unless_all_end_the_game():
    v = torch.tensor([[0.0, 10.0, 20.0], [0.0, 10.0, 20.0]])
    mask = torch.ones(2, 3, dtype=torch.bool)
    terminal = torch.tensor([[False, False, True], [True, True, True]])
    out = rescale_range(v, mask, terminal)
    torch.testing.assert_close(out[0], torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64))
    torch.testing.assert_close(out[1], torch.tensor([0.0, 0.5, 1.0], dtype=torch.float64))


def _choose(weight: float, scaling: str, r: torch.Tensor, h: torch.Tensor) -> int:
    fusion = Fusion("linear", "none", as_schedule(weight), scaling=scaling)
    td = TensorDict({keys.ENV_VALUES: r, keys.HUMAN_VALUES: h}, batch_size=[1])
    return int(FusionModule(fusion, select="greedy")(td)[keys.ACTION])


def test_normalised_linear_weighs_h_against_r_whatever_their_scales():
    r = torch.tensor([[1000.0, 990.0, 0.0]])  # R prefers action 0 by a little (on its scale)
    h = torch.tensor([[-0.01, 0.01, 0.0]])  # H^ prefers action 1
    assert _choose(0.5, "none", r, h) == 0  # raw: H^ is a rounding error next to R
    assert _choose(0.5, "decision", r, h) == 1  # 0.99 + 0.5 * 1 > 1 + 0.5 * 0
    assert _choose(0.0, "decision", r, h) == 0
