"""Every registered Gymnasium id passes Gymnasium's own checker and, through TorchRL's Gym wrapper, TorchRL's
spec check; ``reset(seed=...)`` repeats an episode exactly."""

from __future__ import annotations

import dataclasses
import warnings

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from torchrl.envs import GymWrapper
from torchrl.envs.utils import check_env_specs

import hfrl_torch  # noqa: F401  (registers the ids)
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv, KeepawaySimulator
from hfrl_torch.envs.registration import ENV_IDS
from hfrl_torch.experiment.cli import compose_train
from hfrl_torch.experiment.factories import make_keepaway_config

SMALL = {"hfrl_torch/Tetris-v0": {"width": 8, "height": 8}, "hfrl_torch/Keepaway-v0": {}}


def test_every_registered_id_has_small_options_here():
    assert set(SMALL) == set(ENV_IDS)


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_gymnasium_check_env(env_id):
    env = gym.make(env_id, **SMALL[env_id])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # advice only (an unbounded Box, float32 precision)
        check_env(env.unwrapped)


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_torchrl_check_env_specs(env_id):
    check_env_specs(GymWrapper(gym.make(env_id, **SMALL[env_id])), seed=0)


def _flat(obs) -> np.ndarray:
    if isinstance(obs, dict):
        return np.concatenate([np.ravel(v).astype(np.float64) for _, v in sorted(obs.items())])
    return np.asarray(obs, dtype=np.float64)


def _episode(env: gym.Env, seed: int, steps: int = 15) -> list[np.ndarray]:
    """Observations and rewards of ``steps`` steps after ``reset(seed=seed)``, actions drawn from the mask."""
    obs, info = env.reset(seed=seed)
    rng = np.random.default_rng(0)
    seen = [_flat(obs)]
    for _ in range(steps):
        allowed = np.flatnonzero(info["action_mask"])
        obs, reward, terminated, truncated, info = env.step(int(rng.choice(allowed)))
        seen.append(np.append(_flat(obs), reward))
        if terminated or truncated:
            break
    return seen


@pytest.mark.parametrize("env_id", sorted(ENV_IDS))
def test_a_seeded_reset_repeats_the_episode_after_play(env_id):
    env = gym.make(env_id, **SMALL[env_id]).unwrapped
    first = _episode(env, 123)
    again = _episode(env, 123)  # after the first episode's play (body angles, boards)
    fresh = _episode(gym.make(env_id, **SMALL[env_id]).unwrapped, 123)
    other = _episode(env, 124)
    assert len(first) == len(again) == len(fresh) > 1
    assert all(
        np.array_equal(a, b) and np.array_equal(a, c) for a, b, c in zip(first, again, fresh, strict=True)
    )
    assert not np.array_equal(first[0], other[0])


def test_keepaway_defaults_play_train_py_s_task():
    """The library's keepaway defaults (the Gymnasium id, ``KeepawayEnv()``, ``KeepawaySimulator()``,
    ``KeepawayConfig()``) are the task ``train.py domain=keepaway`` plays, field by field; only how it runs
    (``kernels``) and the decision period (5 cycles when a trainer watches) are train.py's own."""
    cfg = compose_train("domain=keepaway")
    trained = make_keepaway_config(cfg)
    how = {"kernels", "decision_period_cycles"}
    task = [f.name for f in dataclasses.fields(KeepawayConfig) if f.name not in how]
    # the domain config sets every field compared: none of them is left to KeepawayConfig's default
    assert set(task) <= set(cfg.domain)
    assert trained.perception == "server"
    defaults = {
        "hfrl_torch/Keepaway-v0": gym.make("hfrl_torch/Keepaway-v0").unwrapped.env.config,
        "KeepawayEnv()": KeepawayEnv().config,
        "KeepawaySimulator(1)": KeepawaySimulator(1).config,
        "KeepawayConfig()": KeepawayConfig(),
    }
    for where, config in defaults.items():
        for name in task:
            assert getattr(config, name) == getattr(trained, name), (where, name)
