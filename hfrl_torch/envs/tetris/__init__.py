"""Tetris: rules, engines (numba and torch), feature sets and the TorchRL environment."""

from hfrl_torch.envs.tetris.env import TetrisEnv
from hfrl_torch.envs.tetris.features import feature_names, feature_set, feature_size
from hfrl_torch.envs.tetris.rules import TetrisRules

__all__ = ["TetrisEnv", "TetrisRules", "feature_names", "feature_set", "feature_size"]
