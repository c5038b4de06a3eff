"""A user's own tasks and reference policies, outside the package, for ``test_gym_domain.py``:
``domain.make=tests.experiment.gym_task_helpers:make_corridor`` and friends."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

LENGTH = 6  # corridor cells; the agent starts in cell 0 and must walk right to the last


class Corridor(gym.Env):
    """Walk right along a corridor: reward -1 a step, the episode ends at the far end (or after 30 steps)."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(0.0, 1.0, (2,), np.float32)
        self.action_space = gym.spaces.Discrete(2)
        self.cell, self.steps = 0, 0

    def _obs(self) -> np.ndarray:
        return np.array([self.cell / (LENGTH - 1), 1.0], dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.cell, self.steps = 0, 0
        return self._obs(), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.cell = min(LENGTH - 1, self.cell + 1) if int(action) == 1 else max(0, self.cell - 1)
        self.steps += 1
        return self._obs(), -1.0, self.cell == LENGTH - 1, self.steps >= 30, {}


def make_corridor() -> gym.Env:
    """The corridor as a Gymnasium env."""
    return Corridor()


class PixelCorridor(Corridor):
    """The corridor seen as a picture: a 16 x 16 grey frame with the agent's cell lit (a task whose
    observation is a frame, read by the CNN)."""

    def __init__(self) -> None:
        super().__init__()
        self.observation_space = gym.spaces.Box(0, 255, (16, 16, 1), np.uint8)

    def _obs(self) -> np.ndarray:
        frame = np.zeros((16, 16, 1), dtype=np.uint8)
        left = 1 + self.cell * 14 // LENGTH
        frame[6:10, left : left + 2, 0] = 255
        return frame


def make_pixel_corridor() -> gym.Env:
    """The corridor as frames."""
    return PixelCorridor()


class GridCorridor(Corridor):
    """The corridor with a 2-D observation that is no frame (no channel axis): refused in one line."""

    def __init__(self) -> None:
        super().__init__()
        self.observation_space = gym.spaces.Box(0.0, 1.0, (2, 3), np.float32)

    def _obs(self) -> np.ndarray:
        return np.zeros((2, 3), dtype=np.float32)


def make_grid_corridor() -> gym.Env:
    """The corridor with a [2, 3] observation."""
    return GridCorridor()


def walk_right(obs: torch.Tensor) -> torch.Tensor:
    """The corridor's reference: always right (action 1)."""
    return torch.ones(obs.shape[0], dtype=torch.int64)


def walk_right_values(obs: torch.Tensor) -> torch.Tensor:
    """The same reference as action values [B, 2]."""
    return torch.tensor([[0.0, 1.0]]).expand(obs.shape[0], 2)


def wrong_shape(obs: torch.Tensor) -> torch.Tensor:
    """A reference that returns one action for the whole batch."""
    return torch.tensor(1)


class CountDown(EnvBase):
    """A tiny unbatched TorchRL env: a counter from 3 to 0; action 1 counts down, 0 waits; -1 a step."""

    def __init__(self) -> None:
        super().__init__(batch_size=torch.Size([]))
        self.observation_spec = Composite(observation=Bounded(0.0, 3.0, shape=(1,), dtype=torch.float32))
        self.action_spec = Categorical(2, shape=())
        self.reward_spec = Unbounded(shape=(1,))

    def _reset(self, tensordict: TensorDictBase | None) -> TensorDictBase:
        return TensorDict({"observation": torch.tensor([3.0])}, [])

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs = tensordict["observation"] - tensordict["action"].to(torch.float32)
        done = (obs <= 0).reshape(1)
        return TensorDict(
            {
                "observation": obs.clamp(min=0),
                "reward": torch.tensor([-1.0]),
                "done": done,
                "terminated": done,
            },
            [],
        )

    def _set_seed(self, seed: int | None) -> None:
        return None


def make_countdown() -> EnvBase:
    """The counter as a TorchRL env."""
    return CountDown()
