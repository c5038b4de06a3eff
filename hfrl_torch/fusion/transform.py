"""Reward-level fusion: ``FeedbackFusion``, a TorchRL transform that trains the learner on a fused reward.

Where :class:`~hfrl_torch.fusion.schemes.FusedActionSelector` changes which action is taken, this transform
changes the reward the learner sees: Knox & Stone's reward shaping ``R' = R + beta H^`` (AAMAS 2010), the
thesis's linear (eq. 4.2) and exponential (eq. 5.1) rules applied to the reward, or either signal alone. The
environment's own reward is kept, unchanged, under ``env_reward`` for evaluation and logging.

Where H comes from:

- ``estimate_key`` (default ``"human_reward_estimate"``): ``H^(s, a)`` of the action taken, ``[*B, 1]``,
  written by the policy into the tensordict next to the action, before ``env.step``. The transform
  declares it in the state spec (an input, like the action) and in the observation spec, with the default
  0: a reset writes 0, and every step writes 0 into ``next`` so that a policy which does not write a fresh
  estimate fuses with 0 and never with the previous step's (the ``TensorDictPrimer`` pattern, with the
  primer's value reset at every step). An absent estimate reads as 0.
- ``feedback_key`` (e.g. ``keys.FEEDBACK``): the person's reward for this step, ``[*B, 1]``, 0 where none
  was given, written into ``next`` by the env or by an earlier transform of a ``Compose``. It must be
  present when asked for.
- both: the person's own reward where they gave one (nonzero), H^ elsewhere.

Weights come from a :class:`~hfrl_torch.fusion.schedules.WeightSchedule` evaluated at each board's episode
index. Episodes are delimited by done flags: a board's index advances by one after the step whose done flag
is set (that step is fused with its own episode's weight), once per episode even if the board is stepped
again before its reset; a reset clears the flag for the boards it restarts and touches no other board. The
transform never calls ``schedule.end_episode``: a trust schedule is updated by the training loop, which
knows the match rates.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.data import Composite, TensorSpec, Unbounded
from torchrl.envs.transforms import Transform
from torchrl.envs.transforms.utils import _get_reset

from hfrl_torch import keys
from hfrl_torch.fusion.schedules import WeightSchedule, as_schedule
from hfrl_torch.fusion.schemes import REWARD_SCHEMES, fuse_values

__all__ = ["HUMAN_REWARD_ESTIMATE", "FeedbackFusion"]

HUMAN_REWARD_ESTIMATE = keys.HUMAN_REWARD_ESTIMATE


def _float_dtype(dtype: torch.dtype) -> torch.dtype:
    return dtype if dtype.is_floating_point else torch.get_default_dtype()


class FeedbackFusion(Transform):
    """Fuse the env reward R with the person's reward H into the reward the learner sees.

    ``reward <- f(R, H)`` with ``f`` one of :data:`~hfrl_torch.fusion.schemes.REWARD_SCHEMES` (see
    :func:`~hfrl_torch.fusion.schemes.fuse_values`), ``env_reward <- R``. The module docstring says where H is
    read and how episodes are counted.

    :param scheme: ``none``, ``human_only``, ``linear``, ``exponential`` or ``reward_shaping``.
    :param weight: ``w`` / ``beta``: a number, one number per board, or a :class:`WeightSchedule` (per board:
        learners along the env's first batch dimension).
    :param estimate_key: where the policy writes ``H^(s, a)`` (None: not used).
    :param feedback_key: where the person's reward for the step arrives in ``next`` (None: not used).
    :param reward_key: the env reward, replaced by the fused one.
    :param env_reward_key: where the env reward is kept.
    :param done_key: the done flag that ends an episode.
    :param reset_key: the partial-reset flag.

    Offline (``transform(rollout)``), the transform re-fuses a stored trajectory ``[*B, T]`` (time last, as
    ``env.rollout`` and collectors lay it out): R from ``("next", env_reward)`` if present, else
    ``("next", reward)``; episodes counted from 0 by the done flags along time (each done is taken to have
    been followed by a reset). With a constant or annealed weight it reproduces the online fused rewards of a
    rollout that started at episode 0; a trust schedule gives its current trust everywhere.

    Example:
        >>> env = TransformedEnv(TetrisEnv(batch=4), FeedbackFusion("reward_shaping", AnnealedWeight(2.0)))
        >>> td = env.reset()
        >>> td["action"], td["human_reward_estimate"] = policy(td)  # H^ of the chosen placement
        >>> out = env.step(td)["next"]  # out["reward"]: R + beta H^, out["env_reward"]: R
    """

    def __init__(
        self,
        scheme: str = "linear",
        weight: float | Sequence[float] | Tensor | WeightSchedule = 1.0,
        *,
        estimate_key: NestedKey | None = HUMAN_REWARD_ESTIMATE,
        feedback_key: NestedKey | None = None,
        reward_key: NestedKey = keys.REWARD,
        env_reward_key: NestedKey = keys.ENV_REWARD,
        done_key: NestedKey = keys.DONE,
        reset_key: NestedKey = keys.RESET,
    ) -> None:
        if scheme not in REWARD_SCHEMES:
            hint = (
                "; action_biasing and control_sharing act at selection: use FusedActionSelector"
                if scheme in ("action_biasing", "control_sharing")
                else ""
            )
            raise ValueError(
                f"FeedbackFusion scheme={scheme!r} is invalid; allowed: {', '.join(REWARD_SCHEMES)}{hint}"
            )
        if estimate_key is None and feedback_key is None:
            raise ValueError("FeedbackFusion needs estimate_key, feedback_key or both: where to read H from")
        in_keys = [reward_key, *(k for k in (estimate_key, feedback_key) if k is not None)]
        super().__init__(in_keys=in_keys, out_keys=[reward_key, env_reward_key])
        self.scheme = scheme
        self.schedule = as_schedule(weight)
        self.estimate_key = estimate_key
        self.feedback_key = feedback_key
        self.reward_key = reward_key
        self.env_reward_key = env_reward_key
        self.done_key = done_key
        self.reset_key = reset_key
        self._episodes: Tensor | None = None
        self._finished: Tensor | None = None

    @property
    def episodes(self) -> Tensor | None:
        """Each board's episode index (int64, the env's batch shape), or None before the first reset."""
        return self._episodes

    def _counters(self, batch: torch.Size, device: torch.device | None) -> Tensor:
        if self._episodes is None or self._episodes.shape != batch:
            if self._episodes is not None:
                raise ValueError(
                    f"FeedbackFusion counts episodes of batch {tuple(self._episodes.shape)}, got a "
                    f"tensordict of batch {tuple(batch)}"
                )
            self._episodes = torch.zeros(batch, dtype=torch.int64, device=device)
            self._finished = torch.zeros(batch, dtype=torch.bool, device=device)
        return self._episodes

    def _human(self, root: TensorDictBase, nxt: TensorDictBase, reward: Tensor) -> Tensor:
        estimate = feedback = None
        if self.estimate_key is not None:
            estimate = root.get(self.estimate_key, None)
        if self.feedback_key is not None:
            feedback = nxt.get(self.feedback_key, None)
            if feedback is None:
                raise KeyError(
                    f"FeedbackFusion reads the person's reward from ('next', {self.feedback_key!r}), "
                    "which is absent; put the transform that writes it (0 where no feedback) before this one"
                )
        estimate = self._like(estimate, reward, self.estimate_key)
        feedback = self._like(feedback, reward, self.feedback_key)
        if feedback is None:
            return estimate if estimate is not None else torch.zeros_like(reward)
        if estimate is None:
            return feedback
        return torch.where(feedback != 0, feedback, estimate)

    @staticmethod
    def _like(value: Tensor | None, reward: Tensor, key: NestedKey | None) -> Tensor | None:
        if value is None:
            return None
        if value.shape != reward.shape:
            if value.numel() != reward.numel():
                raise ValueError(
                    f"{key!r} has shape {tuple(value.shape)}; expected one per reward, {tuple(reward.shape)}"
                )
            value = value.reshape(reward.shape)
        return value.to(device=reward.device)

    def _done(self, nxt: TensorDictBase) -> Tensor:
        done = nxt.get(self.done_key, None)
        if done is None:
            raise KeyError(
                f"FeedbackFusion counts episodes from ('next', {self.done_key!r}), which is absent"
            )
        batch = nxt.batch_size
        return done.reshape(*batch, -1).any(-1) if done.ndim > len(batch) else done.reshape(batch)

    def _fuse(self, reward: Tensor, human: Tensor, episodes: Tensor) -> Tensor:
        fused = fuse_values(reward, human, self.scheme, self.schedule.value(episodes))
        return fused.to(reward.dtype if self.scheme == "none" else _float_dtype(reward.dtype))

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        reward = next_tensordict.get(self.reward_key)
        human = self._human(tensordict, next_tensordict, reward)
        episodes = self._counters(next_tensordict.batch_size, reward.device)
        next_tensordict.set(self.reward_key, self._fuse(reward, human, episodes))
        next_tensordict.set(self.env_reward_key, reward)
        if self.estimate_key is not None:
            next_tensordict.set(self.estimate_key, torch.zeros_like(reward, dtype=_float_dtype(reward.dtype)))
        done = self._done(next_tensordict).to(episodes.device)
        self._episodes = episodes + (done & ~self._finished).to(torch.int64)
        self._finished = self._finished | done
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        reset = _get_reset(self.reset_key, tensordict).reshape(batch)
        self._counters(batch, tensordict_reset.device)
        self._finished = self._finished & ~reset.to(self._finished.device)
        zero = torch.zeros(*batch, 1, dtype=self._reward_dtype(), device=tensordict_reset.device)
        tensordict_reset.set(self.env_reward_key, zero)
        if self.estimate_key is not None:
            tensordict_reset.set(self.estimate_key, torch.zeros_like(zero, dtype=_float_dtype(zero.dtype)))
        return tensordict_reset

    def _reward_dtype(self) -> torch.dtype:
        parent = self.parent
        if parent is None:
            return torch.get_default_dtype()
        return parent.full_reward_spec[self.reward_key].dtype

    def _reset_on_native_autoreset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Fuse a stored trajectory ``[*B, T]`` after the fact (see the class docstring)."""
        names = tensordict.names if tensordict.batch_dims else []
        if tensordict.batch_dims == 0 or (
            "time" in names and names.index("time") != tensordict.batch_dims - 1
        ):
            raise ValueError(
                f"FeedbackFusion offline needs data [*B, T] with time as the last dimension, got batch "
                f"{tuple(tensordict.batch_size)} with names {names}"
            )
        nxt = tensordict.get("next")
        reward = nxt.get(self.env_reward_key, None)
        if reward is None:
            reward = nxt.get(self.reward_key)
        human = self._human(tensordict, nxt, reward)
        done = self._done(nxt).to(torch.int64)
        episodes = done.cumsum(-1) - done
        nxt.set(self.reward_key, self._fuse(reward, human, episodes))
        nxt.set(self.env_reward_key, reward)
        return tensordict

    def _estimate_spec(self, shape: torch.Size, device: torch.device | None) -> Unbounded:
        return Unbounded(shape=(*shape, 1), dtype=_float_dtype(self._reward_dtype()), device=device)

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if not isinstance(observation_spec, Composite):
            raise TypeError(
                f"FeedbackFusion expects a Composite observation spec, got {type(observation_spec)}"
            )
        parent = self.parent
        if parent is None:
            raise RuntimeError("FeedbackFusion specs need the transform to sit in a TransformedEnv")
        observation_spec[self.env_reward_key] = parent.full_reward_spec[self.reward_key].clone()
        if self.estimate_key is not None:
            observation_spec[self.estimate_key] = self._estimate_spec(
                observation_spec.shape, observation_spec.device
            )
        return observation_spec

    def transform_input_spec(self, input_spec: TensorSpec) -> TensorSpec:
        if self.estimate_key is None:
            return input_spec
        state = input_spec["full_state_spec"]
        if state is None:
            state = Composite(shape=input_spec.shape, device=input_spec.device)
        state[self.estimate_key] = self._estimate_spec(input_spec.shape, input_spec.device)
        input_spec["full_state_spec"] = state
        return input_spec

    def transform_reward_spec(self, reward_spec: TensorSpec) -> TensorSpec:
        if self.scheme == "none":
            return reward_spec
        spec = reward_spec[self.reward_key]
        if not isinstance(spec, Unbounded) or not spec.dtype.is_floating_point:
            reward_spec[self.reward_key] = Unbounded(
                shape=spec.shape, dtype=_float_dtype(spec.dtype), device=spec.device
            )
        return reward_spec

    def get_extra_state(self) -> dict[str, Any]:
        """Episode counters and the schedule's state (plain numbers), for checkpoints."""
        return {
            "episodes": None if self._episodes is None else self._episodes.tolist(),
            "finished": None if self._finished is None else self._finished.tolist(),
            "schedule": self.schedule.state_dict(),
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.schedule.load_state_dict(state["schedule"])
        if state["episodes"] is None:
            self._episodes = self._finished = None
        else:
            self._episodes = torch.tensor(state["episodes"], dtype=torch.int64)
            self._finished = torch.tensor(state["finished"], dtype=torch.bool)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(scheme={self.scheme!r}, weight={self.schedule!r}, "
            f"estimate_key={self.estimate_key!r}, feedback_key={self.feedback_key!r})"
        )
