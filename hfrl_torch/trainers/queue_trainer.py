"""The trainer end of a ``FeedbackQueue``: feedback produced by another thread (the browser trainer).

The producer pushes timestamped ``FeedbackEvent`` objects from its own thread, whenever its person
presses a key; once per step the training loop calls ``give``, which drains what has arrived without
blocking, labels each event with the placement that was on screen when it was given (the latest
placement that happened strictly before the event's time) and hands the events to the agent, whose
credit model does the actual credit assignment from the times. The loop's clock and the producer's
must be the same (``time.time()`` for a live session).
"""

from __future__ import annotations

import bisect

import torch
from tensordict import TensorDictBase

from hfrl_torch.feedback.events import FeedbackEvent, FeedbackQueue
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.base import Events, Trainer, placement_steps


class QueueTrainer(Trainer):
    """Drains a ``FeedbackQueue`` each step and gives its events to the board the producer watches.

    Events keep their own ``source`` and ``time``; ``step`` and ``episode`` are set from the placement
    that happened last before ``time`` (left at -1 for an event older than every placement recorded).

    :param queue: the queue the producer thread fills.
    :param board: the board the producer's events are about (the one shown to the person).
    :param history: how many recent placements are kept for labelling late events.
    :param log: feedback log every event is appended to.
    """

    source = "queue"

    def __init__(
        self, queue: FeedbackQueue, board: int = 0, history: int = 10_000, log: FeedbackLog | None = None
    ) -> None:
        super().__init__(log)
        if board < 0:
            raise ValueError(f"QueueTrainer board must be >= 0, got {board!r}")
        if history < 1:
            raise ValueError(f"QueueTrainer history must be >= 1, got {history!r}")
        self.queue = queue
        self.board = board
        self.history = history
        self._times: list[float] = []
        self._labels: list[tuple[int, int]] = []

    def label(self, event: FeedbackEvent) -> FeedbackEvent:
        """``event`` with the (episode, step) of the placement that happened last before its time."""
        i = bisect.bisect_left(self._times, event.time) - 1
        if i < 0:
            return FeedbackEvent(**{**event.to_dict(), "step": -1, "episode": -1})
        episode, step = self._labels[i]
        return FeedbackEvent(**{**event.to_dict(), "step": step, "episode": episode})

    def give(
        self,
        obs: TensorDictBase,
        action: torch.Tensor,
        time: float,
        episode: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> Events:
        b = obs.batch_size[0]
        if self.board >= b:
            raise ValueError(f"QueueTrainer board={self.board} but the run has {b} boards")
        if self._times and time < self._times[-1]:
            raise ValueError(f"step times must not go back: {time} after {self._times[-1]}")
        self._times.append(float(time))
        self._labels.append((int(episode[self.board]), int(placement_steps(obs)[self.board])))
        if len(self._times) > self.history:
            del self._times[0], self._labels[0]
        events: Events = [[] for _ in range(b)]
        events[self.board] = [self.label(ev) for ev in self.queue.drain()]
        return self._emit(events)
