"""The scripted reference policies shipped in ``examples/`` solve their tasks, as their docstrings say: the
simulated oracle judges against them, so a reference that fails its task would teach a failing policy."""

from __future__ import annotations

import gymnasium as gym
import pytest
import torch

from examples import acrobot, cartpole, mountain_car


def _episode(env_id: str, reference, seed: int) -> tuple[int, bool]:
    """Steps played and whether the episode ended at the task's goal (not at its time limit)."""
    env = gym.make(env_id)
    obs, _ = env.reset(seed=seed)
    steps = 0
    while True:
        action = int(reference(torch.as_tensor(obs, dtype=torch.float32).unsqueeze(0))[0])
        obs, _, terminated, truncated, _ = env.step(action)
        steps += 1
        if terminated or truncated:
            env.close()
            return steps, terminated


@pytest.mark.parametrize(
    ("env_id", "reference", "goal"),
    [
        ("CartPole-v1", cartpole.reference, "limit"),  # balanced to the 500-step limit
        ("MountainCar-v0", mountain_car.reference, "terminated"),  # the flag before 200 steps
        ("Acrobot-v1", acrobot.reference, "terminated"),  # the bar before 500 steps
    ],
)
def test_each_reference_reaches_its_goal_from_seeded_starts(env_id, reference, goal):
    episodes = [_episode(env_id, reference, seed) for seed in range(5)]
    if goal == "limit":
        assert all(steps == 500 and not terminated for steps, terminated in episodes), episodes
    else:
        assert all(terminated for _, terminated in episodes), episodes
