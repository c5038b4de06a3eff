"""Catch, a task of the user's own (docs/tutorial.md): ``domain.make=examples.catch:make`` and
``trainer.reference=examples.catch:reference``.

Balls fall one row a step down a grid ``WIDTH`` columns wide and ``HEIGHT`` rows tall, each from a random
column; the paddle on the bottom row moves left, stays or moves right. A ball caught scores 1, a ball missed
0; an episode is ``BALLS`` balls, so its return is the balls caught (0 to 10). The reference (move under the
ball) catches every ball: ``python evaluate.py domain=gym domain.make=examples.catch:make
policy=examples.catch:reference``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import torch

WIDTH, HEIGHT, BALLS = 5, 5, 10
CELL = 24  # pixels per grid cell in the rendered frames


class Catch(gym.Env):
    """Catch falling balls with a paddle: observations (paddle column, ball column, ball row), each scaled
    to [0, 1]; actions 0 left, 1 stay, 2 right."""

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 5}

    def __init__(self, render_mode: str | None = None) -> None:
        self.observation_space = gym.spaces.Box(0.0, 1.0, (3,), np.float32)
        self.action_space = gym.spaces.Discrete(3)
        self.render_mode = render_mode
        self.paddle, self.ball_x, self.ball_y, self.balls = WIDTH // 2, 0, 0, 0

    def _obs(self) -> np.ndarray:
        scale = (WIDTH - 1, WIDTH - 1, HEIGHT - 1)
        return np.array([self.paddle, self.ball_x, self.ball_y], dtype=np.float32) / np.float32(scale)

    def _drop(self) -> None:
        self.ball_x, self.ball_y = int(self.np_random.integers(WIDTH)), 0

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        self.paddle, self.balls = WIDTH // 2, 0
        self._drop()
        return self._obs(), {}

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict]:
        self.paddle = min(WIDTH - 1, max(0, self.paddle + int(action) - 1))
        self.ball_y += 1
        reward = 0.0
        if self.ball_y == HEIGHT - 1:
            reward = float(self.ball_x == self.paddle)
            self.balls += 1
            self._drop()
        return self._obs(), reward, self.balls == BALLS, False, {}

    def render(self) -> np.ndarray | None:
        """The grid as an RGB frame [HEIGHT * CELL, WIDTH * CELL, 3]: the ball red, the paddle white."""
        if self.render_mode != "rgb_array":
            return None
        frame = np.full((HEIGHT * CELL, WIDTH * CELL, 3), 30, dtype=np.uint8)
        y, x = self.ball_y * CELL, self.ball_x * CELL
        frame[y + 4 : y + CELL - 4, x + 4 : x + CELL - 4] = (220, 50, 50)
        y, x = (HEIGHT - 1) * CELL, self.paddle * CELL
        frame[y + CELL // 2 :, x + 1 : x + CELL - 1] = (240, 240, 240)
        return frame


def make() -> gym.Env:
    """One Catch, made to render RGB frames (so the browser trainer can show it too)."""
    return Catch(render_mode="rgb_array")


def reference(obs: torch.Tensor) -> torch.Tensor:
    """Actions [B] for observations [B, 3]: move toward the ball's column, stay under it."""
    return (torch.sign(obs[..., 1] - obs[..., 0]) + 1).to(torch.int64)
