"""The feedback channel: a trainer's events wait on each board's clock, then enter the tensordict.

Every trainer (simulated, replayed, a person in the browser) puts its events here; the training loop asks
for what is due at each decision and gets a tensordict of K slots per board under the ``keys.FEEDBACK*``
keys: the events that arrived since the board's previous decision, oldest first. That tensordict is what
H^ learns from (``TamerAgent.learn``, ``KeeperTamer.learn``) and what reward-level fusion can read. An event
is due once its time (when it was given, reaction delay included) has come on its board's clock; its time
travels with it, so credit assignment still spreads it over the steps before it. More due events than K
wait for the next call, in order. A full queue grows, so no event is ever dropped.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from tensordict import TensorDict
from torch import Tensor

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.feedback.events import FeedbackEvent, source_kind

__all__ = ["FeedbackChannel"]


class FeedbackChannel:
    """Per-board queues of feedback events on the run's clock, delivered as tensordict entries.

    :param boards: B, the boards (fields) feedback is about; board b's events are credited to board b.
    :param slots: K, the most events one board delivers per call (the trailing size of the entries).
    :param capacity: the events one board can hold waiting before the queues grow.
    """

    def __init__(self, boards: int, slots: int = 4, capacity: int = 64) -> None:
        if boards < 1 or slots < 1 or capacity < slots:
            raise ValueError(
                "FeedbackChannel needs boards >= 1 and capacity >= slots >= 1, "
                f"got {boards}, {slots}, {capacity}"
            )
        self.boards, self.slots, self.capacity = int(boards), int(slots), int(capacity)
        # numpy queues: a step moves a few events, where a torch call costs more than its work
        self._time = np.full((boards, capacity), np.inf)
        self._value = np.zeros((boards, capacity))
        self._source = np.zeros((boards, capacity), dtype=np.int64)
        self._waiting = 0  # events in the queues (a delivery with none due is the common case)
        self._none = self._delivery(np.zeros((boards, slots), dtype=bool), None)

    @property
    def pending(self) -> int:
        """Events waiting on every board."""
        return self._waiting

    @property
    def time(self) -> Tensor:
        """When each queued event was given ``[B, capacity]`` (inf: a free slot); a view of the queue."""
        return torch.from_numpy(self._time)

    @property
    def value(self) -> Tensor:
        """Each queued event's value ``[B, capacity]`` (0 in free slots); a view of the queue."""
        return torch.from_numpy(self._value)

    @property
    def source(self) -> Tensor:
        """Each queued event's ``SOURCE_KINDS`` code ``[B, capacity]``; a view of the queue."""
        return torch.from_numpy(self._source)

    def put(self, values: Tensor, times: Tensor, source: str | Tensor) -> None:
        """Queue one event per board where ``values`` [B] is nonzero, given at ``times`` [B] seconds.

        :param source: who gave them (``"simulated:oracle"``, ``"human:browser"``...), or a ``SOURCE_KINDS``
            code per board.
        """
        values = values.detach().to(device="cpu", dtype=torch.float64).reshape(-1)
        if values.shape[0] != self.boards:
            raise ValueError(f"FeedbackChannel of {self.boards} boards got {values.shape[0]} values")
        v = values.numpy()
        rows = np.flatnonzero(v != 0)
        if rows.size == 0:
            return
        t = times.detach().to(device="cpu", dtype=torch.float64).reshape(-1).numpy()
        if isinstance(source, str):
            codes = np.full(self.boards, source_kind(source), dtype=np.int64)
        else:
            codes = source.detach().to(device="cpu", dtype=torch.int64).reshape(-1).numpy()
        self._queue(rows, t[rows], v[rows], codes[rows])

    def _queue(self, rows: np.ndarray, times: np.ndarray, values: np.ndarray, codes: np.ndarray) -> None:
        """Put events into free slots: board b's j-th event (in the order given) in its j-th free slot."""
        need = np.bincount(rows, minlength=self.boards)
        while bool((np.isinf(self._time).sum(1) < need).any()):
            self._grow()
        free = np.argsort(~np.isinf(self._time), axis=1, kind="stable")
        nth = np.arange(rows.size) - (np.cumsum(need) - need)[rows]  # the event's rank on its board
        slot = free[rows, nth]
        self._time[rows, slot] = times
        self._value[rows, slot] = values
        self._source[rows, slot] = codes
        self._waiting += int(rows.size)

    def _grow(self) -> None:
        """Double every board's queue (a clock that stalled while events kept coming)."""
        self._time = np.concatenate((self._time, np.full_like(self._time, np.inf)), 1)
        self._value = np.concatenate((self._value, np.zeros_like(self._value)), 1)
        self._source = np.concatenate((self._source, np.zeros_like(self._source)), 1)
        self.capacity *= 2

    def put_events(self, events: list[list[FeedbackEvent]]) -> None:
        """Queue the events of one step, one list per board (in the order given)."""
        if len(events) != self.boards:
            raise ValueError(f"FeedbackChannel of {self.boards} boards got events for {len(events)}")
        given = [(b, e) for b, evs in enumerate(events) for e in evs if e.value != 0]
        if not given:
            return
        self._queue(
            np.array([b for b, _ in given], dtype=np.int64),
            np.array([e.time for _, e in given], dtype=np.float64),
            np.array([e.value for _, e in given], dtype=np.float64),
            np.array([source_kind(e.source) for _, e in given], dtype=np.int64),
        )

    def deliver(self, now: Tensor | float) -> TensorDict:
        """The events due by ``now`` (seconds, one clock per board [B] or one for all), oldest first, at most
        K per board, as a ``TensorDict`` [B] of ``keys.FEEDBACK``, ``FEEDBACK_TIME``, ``FEEDBACK_MASK`` and
        ``FEEDBACK_SOURCE``, each [B, K]; they leave the queue. A delivery without an event is one shared
        tensordict: read it, do not write into it."""
        if not self._waiting:
            return self._none
        if isinstance(now, Tensor):
            clock = now.detach().to(device="cpu", dtype=torch.float64).reshape(-1, 1).numpy()
        else:
            clock = float(now)
        due = np.isfinite(self._time) & (self._time <= clock)
        if not due.any():
            return self._none
        order = np.argsort(np.where(due, self._time, np.inf), axis=1, kind="stable")[:, : self.slots]
        taken = np.take_along_axis(due, order, 1)
        out = self._delivery(taken, order)
        rows, cols = taken.nonzero()
        slot = order[rows, cols]
        self._time[rows, slot] = np.inf
        self._value[rows, slot] = 0.0
        self._source[rows, slot] = 0
        self._waiting -= int(rows.size)
        return out

    def _delivery(self, taken: np.ndarray, order: np.ndarray | None) -> TensorDict:
        if order is None:  # no event: empty slots
            value, time = np.zeros(taken.shape), np.full(taken.shape, np.nan)
            source = np.zeros(taken.shape, dtype=np.int64)
        else:
            value = np.where(taken, np.take_along_axis(self._value, order, 1), 0.0)
            time = np.where(taken, np.take_along_axis(self._time, order, 1), np.nan)
            source = np.where(taken, np.take_along_axis(self._source, order, 1), 0)
        return TensorDict(
            {
                keys.FEEDBACK: torch.from_numpy(value),
                keys.FEEDBACK_TIME: torch.from_numpy(time),
                keys.FEEDBACK_MASK: torch.from_numpy(taken),
                keys.FEEDBACK_SOURCE: torch.from_numpy(source),
            },
            batch_size=[self.boards],
        )

    def empty(self) -> TensorDict:
        """A delivery with no event (what a decision with nothing due sees); a new one, to write into."""
        return self._none.clone()

    def state_dict(self) -> dict[str, Any]:
        """The waiting events (so a resumed run delivers them as the uninterrupted one would)."""
        return {
            "time": torch.from_numpy(self._time.copy()),
            "value": torch.from_numpy(self._value.copy()),
            "source": torch.from_numpy(self._source.copy()),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output (same number of boards)."""
        try:
            time, value = state["time"].to(torch.float64), state["value"].to(torch.float64)
            source = state["source"].to(torch.int64)
        except (KeyError, TypeError, AttributeError, ValueError) as e:
            raise CheckpointError(f"bad feedback channel state in the checkpoint ({e!r})") from None
        shape = time.shape
        if shape[0] != self.boards or not (value.shape == source.shape == shape):
            raise CheckpointError(
                f"bad feedback channel state: queues of shape {tuple(shape)} for {self.boards} boards"
            )
        self._time = time.detach().cpu().numpy().copy()
        self._value = value.detach().cpu().numpy().copy()
        self._source = source.detach().cpu().numpy().copy()
        self.capacity = shape[1]
        self._waiting = int(np.isfinite(self._time).sum())
