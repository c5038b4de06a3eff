"""Users' own tasks for the gym browser trainer's tests
(``domain.make=tests.interactive.gym_live_helpers:...``)."""

from __future__ import annotations

import gymnasium as gym


def cartpole_without_frames() -> gym.Env:
    """CartPole made without a render mode: it could render frames, but was not asked to."""
    return gym.make("CartPole-v1")


def cartpole_with_frames() -> gym.Env:
    """CartPole made to render RGB frames, as the browser trainer needs from a user's callable."""
    return gym.make("CartPole-v1", render_mode="rgb_array")
