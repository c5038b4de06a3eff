"""Tetris as a Gymnasium environment (one board), for users of other RL libraries.

``gymnasium.make("hfrl_torch/Tetris-v0", width=10, height=20)`` after ``import hfrl_torch``.
"""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces

from hfrl_torch import keys
from hfrl_torch.envs.tetris.engine_numba import NumbaEngine
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.envs.tetris.pieces import placement_table
from hfrl_torch.envs.tetris.render import render_board
from hfrl_torch.envs.tetris.rules import TetrisRules


class TetrisGymEnv(gym.Env):
    """One Tetris board: action = placement index, observation = afterstate features, mask, board, piece.

    Every index of the ``Discrete(A)`` action space is legal, as Gymnasium users expect: an
    index past the current piece's n placements means placement ``index % n`` (the TorchRL
    env, which exposes its mask in the spec, raises instead).
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 6}

    def __init__(
        self,
        width: int = 10,
        height: int = 20,
        features: str = "bt",
        bag: bool = False,
        spawn_topout: bool = False,
        preview: bool = False,
        render_mode: str | None = None,
    ) -> None:
        self.rules = TetrisRules(width, height, bag=bag, spawn_topout=spawn_topout, preview=preview)
        self.engine = NumbaEngine(self.rules, 1, feature_id(features))
        self.render_mode = render_mode
        a = placement_table(width).max_actions
        f = feature_size(feature_id(features), width)
        obs = {
            keys.AFTERSTATE_FEATURES: spaces.Box(-np.inf, np.inf, (a, f), np.float32),
            keys.AFTERSTATE_TERMINAL: spaces.MultiBinary(a),
            keys.ACTION_MASK: spaces.MultiBinary(a),
            keys.BOARD: spaces.Box(0, 1, (height, width), np.int8),  # TorchRL wraps no 2-D MultiBinary
            keys.PIECE: spaces.Discrete(7),
        }
        if preview:
            obs[keys.NEXT_PIECE] = spaces.Discrete(7)
        self.observation_space = spaces.Dict(obs)
        self.action_space = spaces.Discrete(a)

    def _obs(self) -> dict[str, Any]:
        feats, mask, terminal, _ = self.engine.afterstates()
        out = {
            keys.AFTERSTATE_FEATURES: feats[0].numpy().copy(),
            keys.AFTERSTATE_TERMINAL: terminal[0].numpy().astype(np.int8),
            keys.ACTION_MASK: mask[0].numpy().astype(np.int8),
            keys.BOARD: self.engine.boards()[0].numpy().astype(np.int8),
            keys.PIECE: int(self.engine.pieces[0]),
        }
        if self.rules.preview:
            out[keys.NEXT_PIECE] = int(self.engine.next_pieces()[0])
        return out

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[dict, dict]:
        super().reset(seed=seed)
        game_seed = int(self.np_random.integers(0, 2**62))
        self.engine.reset(torch.ones(1, dtype=torch.bool), torch.tensor([game_seed]))
        self._lines = 0
        return self._obs(), {"action_mask": self._obs()[keys.ACTION_MASK], "game_seed": game_seed}

    def step(self, action: int) -> tuple[dict, float, bool, bool, dict]:
        if not self.action_space.contains(action):
            raise ValueError(f"action={action!r} is invalid; allowed: integers 0..{self.action_space.n - 1}")
        n = int(self.engine.table.num_actions[int(self.engine.pieces[0])])
        lines = int(self.engine.step(torch.tensor([int(action) % n]))[0])
        self._lines += lines
        terminated = not bool(self.engine.alive[0])
        obs = self._obs()
        return (
            obs,
            float(lines),
            terminated,
            False,
            {"lines": self._lines, "action_mask": obs[keys.ACTION_MASK]},
        )

    def render(self) -> np.ndarray | None:
        if self.render_mode == "rgb_array":
            return render_board(self.engine.boards()[0].numpy())
        return None
