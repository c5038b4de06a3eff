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

import numba
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
        shape = (boards, slots)
        self._none = self._entries(
            np.zeros(shape),
            np.full(shape, np.nan),
            np.zeros(shape, dtype=bool),
            np.zeros(shape, dtype=np.int64),
        )

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

    def collect(self, trainer: Any, clock: Tensor) -> Tensor:
        """Queue what a trainer that gives at its own times (a person, a replayed log: ``trainer.poll``) has
        given by each board's ``clock`` [B]; a trainer that judges steps (``give``) has no ``poll``. Returns
        the events queued per board (int64 [B]), for the effort a run books per episode."""
        queued = torch.zeros(self.boards, dtype=torch.int64)
        poll = getattr(trainer, "poll", None)
        while poll is not None:
            values, times = poll(clock)
            given = values.detach().cpu().reshape(-1) != 0
            if not bool(given.any()):
                break
            self.put(values, times, trainer.source)
            queued += given.to(torch.int64)
        return queued

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
        while not _queue_events(self._time, self._value, self._source, rows, times, values, codes):
            self._grow()
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

    def put_board(self, board: int, events: list[FeedbackEvent]) -> None:
        """Queue ``events`` of one board (e.g. a resumed run's presses on the board a person watches)."""
        if not 0 <= board < self.boards:
            raise ValueError(f"FeedbackChannel of {self.boards} boards got events for board {board}")
        self.put_events([events if b == board else [] for b in range(self.boards)])

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
        clocks = np.broadcast_to(clock, (self.boards, 1))[:, 0].astype(np.float64)
        taken = np.zeros((self.boards, self.slots), dtype=np.bool_)
        value = np.zeros((self.boards, self.slots))
        time = np.full((self.boards, self.slots), np.nan)
        source = np.zeros((self.boards, self.slots), dtype=np.int64)
        n = _take_due(self._time, self._value, self._source, clocks, taken, value, time, source)
        if n == 0:
            return self._none
        self._waiting -= n
        return self._entries(value, time, taken, source)

    def _entries(
        self, value: np.ndarray, time: np.ndarray, taken: np.ndarray, source: np.ndarray
    ) -> TensorDict:
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


@numba.njit(cache=True, nogil=True)
def _queue_events(time, value, source, rows, times, values, codes):  # type: ignore[no-untyped-def]
    """Each event into its board's first free slot, in the order given; False (and nothing written) if a
    board has too few free slots."""
    boards, capacity = time.shape
    need = np.zeros(boards, dtype=np.int64)
    for i in range(rows.size):
        need[rows[i]] += 1
    for b in range(boards):
        if need[b]:
            free = 0
            for j in range(capacity):
                free += np.isinf(time[b, j])
            if free < need[b]:
                return False
    for i in range(rows.size):
        b = rows[i]
        j = 0
        while not np.isinf(time[b, j]):
            j += 1
        time[b, j] = times[i]
        value[b, j] = values[i]
        source[b, j] = codes[i]
    return True


@numba.njit(cache=True, nogil=True)
def _take_due(time, value, source, clocks, taken, out_value, out_time, out_source):  # type: ignore[no-untyped-def]
    """Move each board's due events (time <= its clock), oldest first (ties: the lower slot), into its K
    output slots and free their queue slots; returns how many moved."""
    boards, capacity = time.shape
    slots = taken.shape[1]
    moved = 0
    for b in range(boards):
        for k in range(slots):
            best = -1
            for j in range(capacity):
                t = time[b, j]
                if np.isfinite(t) and t <= clocks[b] and (best < 0 or t < time[b, best]):
                    best = j
            if best < 0:
                break
            taken[b, k] = True
            out_value[b, k] = value[b, best]
            out_time[b, k] = time[b, best]
            out_source[b, k] = source[b, best]
            time[b, best] = np.inf
            value[b, best] = 0.0
            source[b, best] = 0
            moved += 1
    return moved
