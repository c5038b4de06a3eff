"""Noisy cross-entropy method."""

from hfrl_torch.agents.cem.cem import CEMConfig, CrossEntropyMethod

__all__ = ["CEMConfig", "CrossEntropyMethod"]
