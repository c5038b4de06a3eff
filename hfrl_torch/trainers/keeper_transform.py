"""``KeeperFeedback``: a keepaway trainer on the TorchRL data path, writing its feedback into ``next``.

The keepaway twin of :class:`~hfrl_torch.trainers.transform.HumanFeedback`. Each field keeps its simulated
clock (seconds, continuous across episodes: the cycles of its steps, and of a new episode's start up to its
first decision). At each step the trainer (the simulated oracle, or a replayed log) judges the deciding
keeper's action at the field's clock; its events wait in a
:class:`~hfrl_torch.feedback.channel.FeedbackChannel` and, once due on the field's clock, come out into
``("next", keys.FEEDBACK*)``, with ``keys.CLOCK`` (when the field's next decision is made) beside them, so a
learner can credit them to its recent decisions.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torchrl.data import Binary, Composite, TensorSpec, Unbounded
from torchrl.envs.transforms import Transform

from hfrl_torch import keys
from hfrl_torch.common.resets import reset_flags
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.trainers.departure import Departure

__all__ = ["KeeperFeedback"]

CYCLES_PER_SECOND = 10.0


class KeeperFeedback(Transform):
    """Write a keepaway trainer's feedback and each field's clock into each step's ``next``.

    :param trainer: ``KeepawayOracle`` or ``KeepawayReplay`` (``give(obs, action, deciding, time, keeper)``,
        ``new_episodes(starting)``; a replay also ``poll(clock)``).
    :param slots: K, the events one field can receive per step (more wait for the next steps).
    :param departure: when the trainer leaves the learner (the episodes its fields finished, or the minutes
        of their clocks together; ``trainer.leave_after``): from then on it judges nothing, and what it gave
        before still arrives. None: it stays.
    """

    def __init__(self, trainer: Any, slots: int = 4, departure: Departure | None = None) -> None:
        out = [keys.FEEDBACK, keys.FEEDBACK_TIME, keys.FEEDBACK_MASK, keys.FEEDBACK_SOURCE, keys.CLOCK]
        super().__init__(in_keys=[keys.ACTION, keys.OBSERVATION, keys.KEEPER, keys.DECIDING], out_keys=out)
        self.trainer, self.slots = trainer, int(slots)
        self.channel: FeedbackChannel | None = None
        self.clock: torch.Tensor | None = None  # [B] seconds
        self.departure = departure or Departure()
        self.episodes = 0  # finished by the fields together

    def _state(self, fields: int) -> FeedbackChannel:
        if self.channel is None:
            self.channel = FeedbackChannel(fields, slots=self.slots)
            self.clock = torch.zeros(fields, dtype=torch.float64)
        return self.channel

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        channel = self._state(batch.numel())
        deciding = tensordict.get(keys.DECIDING).reshape(-1).cpu() & self.present
        values, times = self.trainer.give(
            tensordict.get(keys.OBSERVATION).reshape(batch.numel(), -1),
            tensordict.get(keys.ACTION).reshape(-1),
            deciding,
            self.clock,
            tensordict.get(keys.KEEPER).reshape(-1),
        )
        channel.put(values, times, self.trainer.source)
        cycles = next_tensordict.get(keys.STEP_CYCLES).reshape(-1).cpu().to(torch.float64)
        self.clock = self.clock + cycles / CYCLES_PER_SECOND
        self.episodes += int(next_tensordict.get(keys.DONE).sum())
        channel.collect(self.trainer, self.clock)
        next_tensordict.update(channel.deliver(self.clock).reshape(batch))
        next_tensordict.set(keys.CLOCK, self.clock.clone().reshape(batch))
        return next_tensordict

    @property
    def present(self) -> bool:
        """Whether the trainer still judges: the fields' finished episodes, or their clocks together, are
        short of ``departure``'s."""
        return self.present_at(self.episodes, torch.zeros(1) if self.clock is None else self.clock)

    def present_at(self, episodes: int, clock: torch.Tensor) -> bool:
        """Whether the trainer judged a step taken after ``episodes`` ended episodes at the fields' ``clock``
        (the step's ``keys.CLOCK``): what a learner books as the trainer's time."""
        return self.departure.present_one(episodes, float(clock.sum()))

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        channel = self._state(batch.numel())
        reset = reset_flags(tensordict, keys.RESET, batch).reshape(-1).cpu()
        started = tensordict_reset.get(keys.EPISODE_CYCLES).reshape(-1).cpu().to(torch.float64)
        self.clock = torch.where(reset, self.clock + started / CYCLES_PER_SECOND, self.clock)
        self.trainer.new_episodes(reset)
        tensordict_reset.update(channel.empty().reshape(batch))
        return tensordict_reset.set(keys.CLOCK, self.clock.clone().reshape(batch))

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if not isinstance(observation_spec, Composite):
            raise TypeError(
                f"KeeperFeedback expects a Composite observation spec, got {type(observation_spec)}"
            )
        batch, device = observation_spec.shape, observation_spec.device
        shape = (*batch, self.slots)
        observation_spec[keys.FEEDBACK] = Unbounded(shape=shape, dtype=torch.float64, device=device)
        observation_spec[keys.FEEDBACK_TIME] = Unbounded(shape=shape, dtype=torch.float64, device=device)
        observation_spec[keys.FEEDBACK_MASK] = Binary(
            n=self.slots, shape=shape, dtype=torch.bool, device=device
        )
        observation_spec[keys.FEEDBACK_SOURCE] = Unbounded(shape=shape, dtype=torch.int64, device=device)
        observation_spec[keys.CLOCK] = Unbounded(shape=batch, dtype=torch.float64, device=device)
        return observation_spec

    def get_extra_state(self) -> dict[str, Any]:
        """Each field's clock, the episodes finished, the waiting events and the trainer's state."""
        return {
            "clock": None if self.clock is None else self.clock.clone(),
            "episodes": self.episodes,
            "channel": None if self.channel is None else self.channel.state_dict(),
            "trainer": self.trainer.state_dict(),
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.trainer.load_state_dict(state["trainer"])
        self.episodes = int(state.get("episodes", 0))  # (checkpoints before trainer.leave_after: 0)
        if state["clock"] is not None:
            self._state(state["clock"].numel()).load_state_dict(state["channel"])
            self.clock = state["clock"].clone()

    def __repr__(self) -> str:
        return f"{type(self).__name__}(trainer={type(self.trainer).__name__}, slots={self.slots})"
