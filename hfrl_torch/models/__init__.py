"""Torch modules for value functions and reward models."""

from hfrl_torch.models.linear import LinearValue

__all__ = ["LinearValue"]
