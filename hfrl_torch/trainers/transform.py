"""``HumanFeedback``: a trainer on the TorchRL data path, a transform that writes its feedback into ``next``.

At each step the trainer (a simulated one, a replay, a person through the queue) judges the action taken in
the step's state; its events go into a :class:`~hfrl_torch.feedback.channel.FeedbackChannel` and, once due
on the simulated clock (``seconds_per_step`` per env step), come out into ``("next", keys.FEEDBACK*)``: the
person's reward of the step, next to the environment's, with ``keys.CLOCK`` (when the next action is taken)
so that a learner can credit them to its recent steps. A ``FeedbackFusion(..., feedback_key=keys.FEEDBACK)``
after it in a ``Compose`` fuses the two, so any TorchRL learner (a collector, a replay buffer, a loss) trains
on the fused reward. The training loops of ``train.py`` use the same trainers and channel directly.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.data import Binary, Composite, TensorSpec, Unbounded
from torchrl.envs.transforms import Transform

from hfrl_torch import keys
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.trainers.base import Trainer
from hfrl_torch.trainers.departure import Departure

__all__ = ["HumanFeedback"]


class HumanFeedback(Transform):
    """Write a trainer's feedback into each step's ``next`` (K slots per board; the module docstring).

    :param trainer: the trainer (``trainers.OracleTrainer``, ``HumanLikeTiming``, ``ReplayTrainer``...).
    :param seconds_per_step: the simulated clock's time per env step (a placement with its animation: 1 s).
    :param slots: K, the events one board can receive per step (more wait for the next steps).
    :param score_key: the entry of ``next`` the trainer's ``end_games`` is told at an episode's end (Tetris's
        lines); on a task without it (any Gymnasium env) the trainer is told the end with a score of 0.
    :param departure: when the trainer leaves the learner (its episodes over all boards, or its simulated
        minutes; ``trainer.leave_after``): from then on it judges nothing, and what it gave before still
        arrives. None: it stays.
    """

    def __init__(
        self,
        trainer: Trainer,
        seconds_per_step: float = 1.0,
        slots: int = 4,
        score_key: NestedKey = keys.LINES,
        departure: Departure | None = None,
    ) -> None:
        if not seconds_per_step > 0:
            raise ValueError(f"HumanFeedback seconds_per_step must be > 0, got {seconds_per_step!r}")
        out = [keys.FEEDBACK, keys.FEEDBACK_TIME, keys.FEEDBACK_MASK, keys.FEEDBACK_SOURCE, keys.CLOCK]
        super().__init__(in_keys=[keys.ACTION], out_keys=out)
        self.trainer, self.seconds_per_step, self.slots = trainer, float(seconds_per_step), int(slots)
        self.score_key, self.departure = score_key, departure or Departure()
        self.channel: FeedbackChannel | None = None
        self.steps = 0
        self._games: torch.Tensor | None = None

    def _state(self, boards: int) -> FeedbackChannel:
        if self.channel is None:
            self.channel = FeedbackChannel(boards, slots=self.slots)
            self._games = torch.zeros(boards, dtype=torch.int64)
        return self.channel

    @property
    def clock(self) -> float:
        """The simulated time of the next step's action (seconds)."""
        return self.steps * self.seconds_per_step

    @property
    def present(self) -> bool:
        """Whether the trainer still judges: the learner's episodes over all its boards, or its clock, are
        short of ``departure``'s."""
        games = 0 if self._games is None else int(self._games.sum())
        return self.present_at(games, torch.tensor(self.clock))

    def present_at(self, episodes: int, clock: torch.Tensor) -> bool:
        """Whether the trainer judged a step taken after ``episodes`` ended episodes at ``clock`` (the step's
        ``keys.CLOCK``): what a learner books as the trainer's time."""
        return self.departure.present_one(episodes, float(clock.reshape(-1)[0]))

    def put_board(self, board: int, events: list[FeedbackEvent], boards: int) -> None:
        """Queue events of one of the env's ``boards`` given outside the trainer's turn (a resumed run's
        presses it has not learned yet); they come out once due on the clock."""
        self._state(boards).put_board(board, events)

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        batch = tensordict.batch_size
        channel = self._state(batch.numel())
        if self.present:
            flat = tensordict.reshape(-1)
            events = self.trainer.give(flat, flat.get(keys.ACTION).reshape(-1), self.clock, self._games)
            channel.put_events(events)
        self.steps += 1
        next_tensordict.update(channel.deliver(self.clock).reshape(batch))
        next_tensordict.set(keys.CLOCK, torch.full(batch, self.clock, dtype=torch.float64))
        done = next_tensordict.get(keys.DONE).reshape(-1)
        if bool(done.any()):
            score = next_tensordict.get(self.score_key, None)
            score = torch.zeros(done.shape[0]) if score is None else score.reshape(-1)
            self.trainer.end_games(done, score)
            self._games += done.to(torch.int64)
        return next_tensordict

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        tensordict_reset.update(self._state(batch.numel()).empty().reshape(batch))
        return tensordict_reset.set(keys.CLOCK, torch.full(batch, self.clock, dtype=torch.float64))

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        shape, device = (*observation_spec.shape, self.slots), observation_spec.device
        if not isinstance(observation_spec, Composite):
            raise TypeError(
                f"HumanFeedback expects a Composite observation spec, got {type(observation_spec)}"
            )
        observation_spec[keys.FEEDBACK] = Unbounded(shape=shape, dtype=torch.float64, device=device)
        observation_spec[keys.FEEDBACK_TIME] = Unbounded(shape=shape, dtype=torch.float64, device=device)
        observation_spec[keys.FEEDBACK_MASK] = Binary(
            n=self.slots, shape=shape, dtype=torch.bool, device=device
        )
        observation_spec[keys.FEEDBACK_SOURCE] = Unbounded(shape=shape, dtype=torch.int64, device=device)
        observation_spec[keys.CLOCK] = Unbounded(
            shape=observation_spec.shape, dtype=torch.float64, device=device
        )
        return observation_spec

    def get_extra_state(self) -> dict[str, Any]:
        """The clock, each board's game count, the waiting events and the trainer's state."""
        return {
            "steps": self.steps,
            "games": None if self._games is None else self._games.clone(),
            "channel": None if self.channel is None else self.channel.state_dict(),
            "trainer": self.trainer.state_dict(),
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.steps = int(state["steps"])
        self.trainer.load_state_dict(state["trainer"])
        if state["channel"] is not None:
            self._state(state["games"].numel()).load_state_dict(state["channel"])
            self._games = state["games"].clone()

    def __repr__(self) -> str:
        trainer = type(self.trainer).__name__
        return (
            f"{type(self).__name__}(trainer={trainer}, seconds_per_step={self.seconds_per_step}, "
            f"departure={self.departure!r})"
        )
