"""The value proxy on any task (``domain=gym trainer=value_proxy``): feedback from the advantage of the action
taken under a reference's action values, on constructed values."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.trainers.reference_value_proxy import ReferenceValueProxy, action_values


def _values(obs: torch.Tensor) -> torch.Tensor:
    """Action values [B, 3]: 0, 1 and 2 times the observation's first entry."""
    return obs[:, :1].to(torch.float64) * torch.tensor([0.0, 1.0, 2.0])


def _obs(*first: float) -> TensorDict:
    x = torch.tensor([[f, 0.0] for f in first])
    return TensorDict({keys.OBSERVATION: x}, [len(first)])


def test_the_sign_of_the_advantage_over_the_mean_is_the_feedback():
    proxy = ReferenceValueProxy(_values, 3, reaction=0.5)
    obs, episode = _obs(1.0, 1.0, 1.0, 0.0), torch.zeros(4, dtype=torch.int64)
    events = proxy.give(obs, torch.tensor([2, 0, 1, 2]), 3.0, episode)
    # board 0: 2 - 1 > 0; board 1: 0 - 1 < 0; board 2: the mean itself; board 3: every action worth 0
    assert [[e.value for e in board] for board in events] == [[1.0], [-1.0], [], []]
    assert events[0][0].time == pytest.approx(3.5) and events[0][0].source == "simulated:value_proxy"
    assert proxy.given == 2


def test_scaled_feedback_is_the_advantage_times_the_scale_clipped():
    proxy = ReferenceValueProxy(_values, 3, mode="scaled", scale=2.0)
    events = proxy.give(_obs(1.5, 1e6), torch.tensor([2, 0]), 0.0, torch.zeros(2, dtype=torch.int64))
    assert events[0][0].value == pytest.approx(3.0)  # 2 x (3.0 - 1.5)
    assert events[1][0].value == -1000.0  # clipped to the largest a FeedbackEvent holds


def test_only_finite_action_values_of_the_right_shape_are_taken():
    obs = torch.zeros(2, 2)
    with pytest.raises(ValueError, match=r"needs float action values \[2, 3\]"):
        action_values(lambda o: torch.tensor([0, 1]), obs, 3)  # actions, not values
    with pytest.raises(ValueError, match=r"needs float action values \[2, 3\]"):
        action_values(lambda o: torch.zeros(2, 2), obs, 3)
    with pytest.raises(ValueError, match="not finite"):
        action_values(lambda o: torch.full((2, 3), float("nan")), obs, 3)
    with pytest.raises(ValueError, match=r"mode='loud' is invalid; allowed: sign, scaled"):
        ReferenceValueProxy(_values, 3, mode="loud")
