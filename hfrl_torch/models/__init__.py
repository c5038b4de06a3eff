"""Torch modules for value functions and reward models."""

from hfrl_torch.models.linear import LinearValue
from hfrl_torch.models.reward_model import LinearRewardModel

__all__ = ["LinearRewardModel", "LinearValue"]
