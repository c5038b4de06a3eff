"""Gymnasium registration of the project's environments (lazy: nothing heavy is imported)."""

from __future__ import annotations

import gymnasium as gym

ENV_IDS = {
    "hfrl_torch/Tetris-v0": "hfrl_torch.envs.tetris.gym_env:TetrisGymEnv",
    "hfrl_torch/Keepaway-v0": "hfrl_torch.envs.keepaway.gym_env:KeepawayGymEnv",
}


def register_envs() -> None:
    """Register every env id once (safe to call again)."""
    for env_id, entry_point in ENV_IDS.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point)
