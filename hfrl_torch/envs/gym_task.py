"""Any Gymnasium task (or a TorchRL env of the user's) as a batch of B boards on TorchRL's data path.

``domain=gym``: a registered Gymnasium id (``gym.make``) or a user's callable returning a Gymnasium env or a
TorchRL ``EnvBase``. B copies of a Gymnasium env run in one ``gymnasium.vector.SyncVectorEnv`` (same-step
autoreset) behind TorchRL's ``GymWrapper``, with index actions (``categorical_action_encoding``). Measured on
CartPole-v1, B = 8, random actions, this 2-core machine under load: the synchronous vector env ran 800-880
frames/s and started in 0.4 s; ``SerialEnv`` of 8 ``GymEnv`` 430-460 frames/s; ``GymEnv(num_envs=8)``
(gymnasium's asynchronous vector env, a process per copy) about 1270 frames/s once started but took
minutes to start its 8 workers on 2 busy cores, so the synchronous vector env is the one used. A user's
unbatched ``EnvBase`` runs as B copies in a ``SerialEnv``.

A person watching the task in the browser (``trainer=interactive``) sees board 0 rendered as RGB frames:
:meth:`GymTask.make_watched` makes that copy with ``render_mode="rgb_array"`` (or checks that the user's
callable did) and ``make_gym_batch(..., first=)`` plays it as board 0; :func:`first_frame` renders one
frame to check that the task can be shown at all.
"""

from __future__ import annotations

import importlib
import os
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from torchrl.data import Categorical
from torchrl.envs import EnvBase, GymWrapper, SerialEnv

from hfrl_torch import keys
from hfrl_torch.common.frames import image_shape

__all__ = ["RGB", "GymTask", "TaskSpaces", "first_frame", "make_gym_batch", "task_spaces"]

RGB = "rgb_array"  # the render mode whose frames the browser trainer shows


@dataclass(frozen=True)
class GymTask:
    """Which task a ``domain=gym`` run plays.

    :param env_id: a registered Gymnasium id (used when ``make`` is None).
    :param make: a callable returning a Gymnasium env or an unbatched TorchRL ``EnvBase`` (an unregistered
        task; B copies of an ``EnvBase`` run in a ``SerialEnv``).
    :param max_episode_steps: ``gym.make``'s time limit for ``env_id`` (None: the id's own).
    :param kwargs: further keyword arguments of ``gym.make``.
    """

    env_id: str | None = None
    make: Callable[[], Any] | None = None
    max_episode_steps: int | None = None
    kwargs: tuple[tuple[str, Any], ...] = ()

    @property
    def label(self) -> str:
        """How the task is named in reports."""
        if self.make is not None:
            return f"{getattr(self.make, '__module__', '?')}:{getattr(self.make, '__qualname__', '?')}"
        return str(self.env_id)

    def make_one(self) -> Any:
        """One instance: a Gymnasium env or a TorchRL ``EnvBase``."""
        if self.make is not None:
            return self.make()
        return self._gym_make()

    def _gym_make(self, **more: Any) -> gym.Env:
        """``gym.make`` of ``env_id`` with the task's time limit and keyword arguments, and ``more``."""
        register_ale(str(self.env_id))
        extra = dict(self.kwargs)
        if self.max_episode_steps is not None:
            extra["max_episode_steps"] = int(self.max_episode_steps)
        return gym.make(str(self.env_id), **extra, **more)

    def make_watched(self) -> gym.Env:
        """One instance that renders its frames as RGB arrays (``render_mode="rgb_array"``), for a person to
        watch: a registered id is made so; a callable must return a Gymnasium env made so. ``ValueError``
        saying why not (the instance closed) otherwise."""
        # frames drawn off screen need no window or sound: without these, pygame's SDL probes the display and
        # sound devices (and prints errors) on a machine without them; a value of the user's is kept
        os.environ.setdefault("SDL_VIDEODRIVER", "dummy")
        os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
        if self.make is None:
            try:
                env = self._gym_make(render_mode=RGB)
            except TypeError:  # an env of the old API, which takes no render_mode
                raise ValueError(f"cannot be made with render_mode={RGB!r}") from None
        else:
            env = self.make()
        why = _not_rgb(env)
        if why is not None:
            if hasattr(env, "close"):
                env.close()
            raise ValueError(why)
        return env


def register_ale(env_id: str) -> None:
    """Register the Atari games (``ALE/<Game>-v5``) with Gymnasium before an ``ALE/`` id is made: ale-py
    ships them and their ROMs but registers them only when asked. ``gym.error.Error`` if it is missing."""
    if not env_id.startswith("ALE/"):
        return
    try:  # optional: only Atari tasks need it
        ale_py = importlib.import_module("ale_py")
    except ImportError:
        raise gym.error.Error(
            f"{env_id!r} is an Atari game, which needs ale-py: pip install ale-py"
        ) from None
    gym.register_envs(ale_py)


@dataclass(frozen=True)
class TaskSpaces:
    """What a learner needs to know of a task: the observation's shape and length, the actions, the bounds.

    A vector observation has ``observation_shape == (S,)``; a frame has ``(H, W, C)`` (channels last, the
    networks read it through :class:`~hfrl_torch.models.cnn.ActionCNN`), with ``observation_size`` the
    number of its values."""

    observation_size: int
    actions: int
    low: torch.Tensor  # [S] float32 (-inf where unbounded); [1] for a frame (its smallest pixel value)
    high: torch.Tensor  # [S]; [1] for a frame (its largest)
    sample: torch.Tensor  # [2, *observation_shape] float32: the observations of two resets (seeds 0, 1)
    observation_shape: tuple[int, ...] = ()

    @property
    def frame(self) -> tuple[int, int, int] | None:
        """``(H, W, C)`` where the observation is a frame, else None."""
        return image_shape(self.observation_shape)


def _gym_spaces(env: gym.Env) -> TaskSpaces:
    act, obs = env.action_space, env.observation_space
    if not isinstance(act, gym.spaces.Discrete):
        raise ValueError(f"has a {_space_kind(act)} action space ({act}); agent=dqn needs a discrete one")
    if int(act.start) != 0:
        raise ValueError(f"has actions {act} starting at {int(act.start)}; allowed: Discrete(n) from 0")
    frame = image_shape(obs.shape) if isinstance(obs, gym.spaces.Box) else None
    if not isinstance(obs, gym.spaces.Box) or (len(obs.shape) != 1 and frame is None):
        raise ValueError(
            f"has observations {obs}; allowed: a vector (Box of one dimension) or a frame "
            "(Box [height, width, 1, 3 or 4 channels])"
        )
    low = torch.as_tensor(obs.low, dtype=torch.float32)
    high = torch.as_tensor(obs.high, dtype=torch.float32)
    if frame is not None:
        low, high = low.min().reshape(1), high.max().reshape(1)
    sample = torch.stack([torch.as_tensor(env.reset(seed=i)[0], dtype=torch.float32) for i in (0, 1)])
    return TaskSpaces(
        int(np.prod(obs.shape)), int(act.n), low, high, sample, tuple(int(d) for d in obs.shape)
    )


def _not_rgb(env: Any) -> str | None:
    """Why ``env`` cannot show a person RGB frames (None: it can)."""
    if not isinstance(env, gym.Env):
        return (
            f"returned a {type(env).__name__}: the browser trainer shows a Gymnasium env's frames "
            f"(render_mode={RGB!r})"
        )
    modes = list(env.metadata.get("render_modes", []))
    if RGB not in modes:
        return (
            f"renders no RGB frames (its render modes: {modes or 'none'}); the browser trainer needs {RGB!r}"
        )
    if env.render_mode != RGB:
        return (
            f"was made with render_mode={env.render_mode!r}; the browser trainer needs render_mode={RGB!r} "
            f"(e.g. gym.make(..., render_mode={RGB!r}))"
        )
    return None


def first_frame(env: gym.Env) -> np.ndarray:
    """The frame ``env`` (made with ``render_mode="rgb_array"``) renders after ``reset(seed=0)``: [H, W, 3]
    uint8; ``ValueError`` naming what it rendered instead."""
    env.reset(seed=0)
    frame = env.render()
    shape = getattr(frame, "shape", None)
    if not isinstance(frame, np.ndarray) or frame.dtype != np.uint8 or frame.ndim != 3 or shape[2] != 3:
        what = f"an array of shape {list(shape)} and type {frame.dtype}" if shape is not None else repr(frame)
        raise ValueError(f"rendered {what[:80]}; the browser trainer shows [height, width, 3] uint8 frames")
    if min(shape[:2]) < 1:
        raise ValueError(f"rendered an empty frame of shape {list(shape)}")
    return frame


def _space_kind(space: Any) -> str:
    return "continuous" if isinstance(space, gym.spaces.Box) else type(space).__name__


def _torchrl_spaces(env: EnvBase) -> TaskSpaces:
    spec = env.action_spec
    if not isinstance(spec, Categorical):
        raise ValueError(
            f"has a {type(spec).__name__} action spec; agent=dqn needs index actions (torchrl Categorical)"
        )
    obs = env.observation_spec.get(keys.OBSERVATION, None)
    if obs is None or len(obs.shape) != 1:
        raise ValueError(f"needs a vector entry {keys.OBSERVATION!r} in its observation spec")
    size = int(obs.shape[-1])
    space = getattr(obs, "space", None)
    low = getattr(space, "low", None)
    high = getattr(space, "high", None)
    inf = torch.full((size,), torch.inf)
    low = -inf if low is None else torch.as_tensor(low, dtype=torch.float32).expand(size).clone()
    high = inf if high is None else torch.as_tensor(high, dtype=torch.float32).expand(size).clone()
    if env.batch_size != torch.Size([]):
        raise ValueError(f"returned an env of batch size {list(env.batch_size)}; allowed: unbatched ([])")
    sample = torch.stack([env.reset()[keys.OBSERVATION].to(torch.float32).reshape(size) for _ in (0, 1)])
    return TaskSpaces(size, int(spec.space.n), low, high, sample, (size,))


def task_spaces(task: GymTask) -> TaskSpaces:
    """Build one instance and read its spaces; ``ValueError`` naming what is unsupported (continuous
    actions, non-vector observations), ``gymnasium.error.Error`` for an unknown id."""
    env = task.make_one()
    try:
        if isinstance(env, EnvBase):
            return _torchrl_spaces(env)
        if isinstance(env, gym.Env):
            return _gym_spaces(env)
        raise ValueError(f"returned a {type(env).__name__}, not a Gymnasium env or a TorchRL EnvBase")
    finally:
        if hasattr(env, "close"):
            env.close()


def make_gym_batch(
    task: GymTask, boards: int, seed: int | None = None, first: gym.Env | None = None
) -> EnvBase:
    """``boards`` instances of ``task`` as one TorchRL env with ``batch_size=[boards]`` and index actions
    (the module docstring says how), seeded when ``seed`` is given; ``first``: an instance already made to
    play as board 0 (the one a person watches, :meth:`GymTask.make_watched`)."""
    first = task.make_one() if first is None else first
    if isinstance(first, EnvBase):
        first.close()  # SerialEnv makes its own from the factory
        env = SerialEnv(boards, task.make_one)
    else:  # the instance made to tell the kinds apart is the first of the vector (a task may be slow to make)
        vector = gym.vector.SyncVectorEnv(
            [lambda: first] + [task.make_one] * (boards - 1),
            autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
        )
        env = GymWrapper(vector, categorical_action_encoding=True)
    if seed is not None:
        env.set_seed(int(seed))
    return env
