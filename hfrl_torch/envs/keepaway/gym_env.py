"""A thin Gymnasium wrapper around one keepaway field, registered as "hfrl_torch/Keepaway-v0"."""

from __future__ import annotations

from typing import Any, ClassVar

import gymnasium
import numpy as np
import torch
from gymnasium import spaces
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.envs.keepaway.env import EPISODE_END_REWARDS, STEP_CYCLES, KeepawayEnv
from hfrl_torch.envs.keepaway.render import render_rgb

ENV_ID = "hfrl_torch/Keepaway-v0"


class KeepawayGymEnv(gymnasium.Env):
    """One keepaway field (B = 1) with the Gymnasium API; options as for :class:`KeepawayEnv`.

    ``info`` carries ``keeper``, ``action_mask``, ``episode_cycles``, ``end_cause``,
    ``episode_end_rewards`` and ``step_cycles``. ``reset(seed=s)`` starts afresh, as a new
    ``KeepawayGymEnv(seed=s)`` would: the simulator carries the players' body angles from one episode
    to the next, so re-seeding its generator alone would not repeat the episode.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(self, render_mode: str | None = None, seed: int = 0, **options: Any) -> None:
        self._options = options
        self.env = KeepawayEnv(1, seed=seed, **options)
        cfg = self.env.config
        self.observation_space = spaces.Box(-np.inf, np.inf, shape=(cfg.num_state_vars,), dtype=np.float32)
        self.action_space = spaces.Discrete(cfg.num_actions)
        self.render_mode = render_mode
        self._td: TensorDict | None = None

    def _info(self, td: TensorDict) -> dict[str, Any]:
        return {
            "keeper": int(td[keys.KEEPER][0]),
            "action_mask": td[keys.ACTION_MASK][0].cpu().numpy(),
            "episode_cycles": int(td[keys.EPISODE_CYCLES][0]),
            "end_cause": int(td[keys.END_CAUSE][0]),
            "episode_end_rewards": td[EPISODE_END_REWARDS][0].cpu().numpy(),
            "step_cycles": int(td[STEP_CYCLES][0]),
        }

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new episode; returns the first decision's state variables and info."""
        super().reset(seed=seed)
        if seed is not None:
            self.env = KeepawayEnv(1, seed=seed, **self._options)
        self._td = self.env.reset()
        return self._td[keys.OBSERVATION][0].cpu().numpy(), self._info(self._td)

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hand ``action`` to the keeper with the ball and run to the next decision."""
        if self._td is None:
            raise RuntimeError("call reset() before step()")
        td = self._td.clone()
        td.set(keys.ACTION, torch.tensor([int(action)], device=self.env.device))
        out = self.env.step(td)["next"]
        self._td = out
        terminated = bool(out[keys.TERMINATED][0, 0])
        return (
            out[keys.OBSERVATION][0].cpu().numpy(),
            float(out[keys.REWARD][0, 0]),
            terminated,
            False,
            self._info(out),
        )

    def render(self) -> np.ndarray | None:
        """The field as an RGB array when ``render_mode == "rgb_array"``."""
        if self.render_mode != "rgb_array":
            return None
        return render_rgb(self.env.sim.state, 0, self.env.config)


def register_keepaway() -> None:
    """Register ``ENV_ID`` with Gymnasium (idempotent; ``import hfrl_torch`` already does it)."""
    from hfrl_torch.envs.registration import register_envs

    register_envs()
