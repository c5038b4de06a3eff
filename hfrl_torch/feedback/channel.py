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
        self.time = torch.full((boards, capacity), torch.inf, dtype=torch.float64)
        self.value = torch.zeros(boards, capacity, dtype=torch.float64)
        self.source = torch.zeros(boards, capacity, dtype=torch.int64)
        self._waiting = 0  # events in the queues (a delivery with none due is the common case)
        self._none = self._delivery(torch.zeros(boards, slots, dtype=torch.bool), None)

    @property
    def pending(self) -> int:
        """Events waiting on every board."""
        return self._waiting

    def put(self, values: Tensor, times: Tensor, source: str | Tensor) -> None:
        """Queue one event per board where ``values`` [B] is nonzero, given at ``times`` [B] seconds.

        :param source: who gave them (``"simulated:oracle"``, ``"human:browser"``...), or a ``SOURCE_KINDS``
            code per board.
        """
        values = values.detach().to(device="cpu", dtype=torch.float64).reshape(-1)
        if values.shape[0] != self.boards:
            raise ValueError(f"FeedbackChannel of {self.boards} boards got {values.shape[0]} values")
        new = values != 0
        if not bool(new.any()):
            return
        times = times.detach().to(device="cpu", dtype=torch.float64).reshape(-1)
        if isinstance(source, str):
            codes = torch.full((self.boards,), source_kind(source), dtype=torch.int64)
        else:
            codes = source.detach().to(device="cpu", dtype=torch.int64).reshape(-1)
        if bool((new & torch.isfinite(self.time).all(1)).any()):
            self._grow()
        free = torch.isinf(self.time).to(torch.int8).argmax(1)
        rows = new.nonzero().squeeze(-1)
        self.time[rows, free[rows]] = times[rows]
        self.value[rows, free[rows]] = values[rows]
        self.source[rows, free[rows]] = codes[rows]
        self._waiting += int(rows.numel())

    def _grow(self) -> None:
        """Double every board's queue (a clock that stalled while events kept coming)."""
        self.time = torch.cat((self.time, torch.full_like(self.time, torch.inf)), 1)
        self.value = torch.cat((self.value, torch.zeros_like(self.value)), 1)
        self.source = torch.cat((self.source, torch.zeros_like(self.source)), 1)
        self.capacity *= 2

    def put_events(self, events: list[list[FeedbackEvent]]) -> None:
        """Queue the events of one step, one list per board (in the order given)."""
        if len(events) != self.boards:
            raise ValueError(f"FeedbackChannel of {self.boards} boards got events for {len(events)}")
        # all at once, as one ``put`` per round would: board b's j-th event takes its j-th free slot
        given = [(b, e) for b, evs in enumerate(events) for e in evs if e.value != 0]
        if not given:
            return
        rows = torch.tensor([b for b, _ in given], dtype=torch.int64)
        need = torch.bincount(rows, minlength=self.boards)
        while bool((torch.isinf(self.time).sum(1) < need).any()):
            self._grow()
        free = torch.isinf(self.time).to(torch.int8).argsort(dim=1, descending=True, stable=True)
        nth = torch.arange(len(given)) - (need.cumsum(0) - need)[rows]  # the event's rank on its board
        slot = free[rows, nth]
        self.time[rows, slot] = torch.tensor([e.time for _, e in given], dtype=torch.float64)
        self.value[rows, slot] = torch.tensor([e.value for _, e in given], dtype=torch.float64)
        self.source[rows, slot] = torch.tensor([source_kind(e.source) for _, e in given], dtype=torch.int64)
        self._waiting += len(given)

    def deliver(self, now: Tensor | float) -> TensorDict:
        """The events due by ``now`` (seconds, one clock per board [B] or one for all), oldest first, at most
        K per board, as a ``TensorDict`` [B] of ``keys.FEEDBACK``, ``FEEDBACK_TIME``, ``FEEDBACK_MASK`` and
        ``FEEDBACK_SOURCE``, each [B, K]; they leave the queue. A delivery without an event is one shared
        tensordict: read it, do not write into it."""
        if not self._waiting:
            return self._none
        clock = torch.as_tensor(now, dtype=torch.float64).reshape(-1).expand(self.boards)
        due = torch.isfinite(self.time) & (self.time <= clock.unsqueeze(1))
        if not bool(due.any()):
            return self._none
        order = torch.where(due, self.time, torch.inf).argsort(dim=1, stable=True)[:, : self.slots]
        taken = due.gather(1, order)
        out = self._delivery(taken, order)
        rows, cols = taken.nonzero(as_tuple=True)
        slot = order[rows, cols]
        self.time[rows, slot] = torch.inf
        self.value[rows, slot] = 0.0
        self.source[rows, slot] = 0
        self._waiting -= int(rows.numel())
        return out

    def _delivery(self, taken: Tensor, order: Tensor | None) -> TensorDict:
        if order is None:  # no event: empty slots
            value, time = torch.zeros(taken.shape, dtype=torch.float64), torch.full(taken.shape, torch.nan)
            source = torch.zeros(taken.shape, dtype=torch.int64)
        else:
            value = torch.where(taken, self.value.gather(1, order), 0.0)
            time = torch.where(taken, self.time.gather(1, order), torch.nan)
            source = torch.where(taken, self.source.gather(1, order), 0)
        return TensorDict(
            {
                keys.FEEDBACK: value,
                keys.FEEDBACK_TIME: time.to(torch.float64),
                keys.FEEDBACK_MASK: taken,
                keys.FEEDBACK_SOURCE: source,
            },
            batch_size=[self.boards],
        )

    def empty(self) -> TensorDict:
        """A delivery with no event (what a decision with nothing due sees); a new one, to write into."""
        return self._none.clone()

    def state_dict(self) -> dict[str, Any]:
        """The waiting events (so a resumed run delivers them as the uninterrupted one would)."""
        return {
            "time": self.time.clone(),
            "value": self.value.clone(),
            "source": self.source.clone(),
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
        self.time, self.value, self.source = time.clone(), value.clone(), source.clone()
        self.capacity = shape[1]
        self._waiting = int(torch.isfinite(self.time).sum())
