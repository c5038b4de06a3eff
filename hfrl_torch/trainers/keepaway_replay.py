"""Replay of a recorded keepaway feedback log on a new run (what a trainer gave in an earlier session).

Keepaway decisions come every 500 ms and differ from run to run, so events are matched by time, not by
decision: an event recorded on field f at simulated second t (its arrival time) reaches field f of the new
run when that field's clock passes t, and is credited there like a live press (gamma credit over the
decisions of the last 500 ms). Events of a batched run's log name their field (``"<session>/board<f>"``)
and go to field f % fields; events of a one-field session (the browser trainer's) go to every field.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from typing import Any

import torch
from torch import Tensor

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.trainers.base import board_of, board_session

SOURCE = "replay"


class KeepawayReplay:
    """Gives a recorded log's events again on each field's simulated clock (source ``replay``).

    :param events: the recorded events (e.g. ``load_feedback_log(path)``).
    :param fields: B, the fields of the new run.
    :param log: feedback log every replayed event is appended to.
    """

    source = SOURCE

    def __init__(self, events: Iterable[FeedbackEvent], fields: int, log: FeedbackLog | None = None) -> None:
        if fields < 1:
            raise ValueError(f"KeepawayReplay needs fields >= 1, got {fields}")
        per_field: list[list[tuple[float, float]]] = [[] for _ in range(fields)]
        for ev in events:
            board = board_of(ev.session)
            targets = range(fields) if board is None else [board % fields]
            for f in targets:
                per_field[f].append((ev.time, ev.value))
        width = max(1, max(len(p) for p in per_field))
        self.times = torch.full((fields, width), torch.inf, dtype=torch.float64)
        self.values = torch.zeros(fields, width, dtype=torch.float64)
        for f, recorded in enumerate(per_field):
            recorded.sort()
            if recorded:
                self.times[f, : len(recorded)] = torch.tensor([t for t, _ in recorded], dtype=torch.float64)
                self.values[f, : len(recorded)] = torch.tensor([v for _, v in recorded], dtype=torch.float64)
        self.next = torch.zeros(fields, dtype=torch.int64)
        self.fields, self.log = fields, log
        self.given = 0

    @classmethod
    def from_log(
        cls, path: str | os.PathLike[str], fields: int, log: FeedbackLog | None = None
    ) -> KeepawayReplay:
        """A replay of the feedback log at ``path`` (every session in it)."""
        return cls(load_feedback_log(path), fields, log)

    def new_episodes(self, starting: Tensor) -> None:
        """Nothing to draw: the log says when its trainer spoke."""

    def give(
        self, obs: Tensor, action: Tensor, deciding: Tensor, time: Tensor, keeper: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """No judgement at decisions: every event comes through :meth:`poll`."""
        zeros = torch.zeros(action.shape[0], dtype=torch.float64)
        return zeros, zeros.clone()

    def poll(self, clock: Tensor) -> tuple[Tensor, Tensor]:
        """The next recorded event of each field whose time has come on its ``clock`` [B] (seconds)."""
        at = self.next.clamp(max=self.times.shape[1] - 1).unsqueeze(1)
        t = self.times.gather(1, at).squeeze(1)
        due = (self.next < self.times.shape[1]) & (t <= clock.cpu().to(torch.float64))
        values = torch.where(due, self.values.gather(1, at).squeeze(1), 0.0)
        times = torch.where(due, t, 0.0)
        self.next += due.long()
        self.given += int(due.sum())
        if self.log is not None and bool(due.any()):
            session = self.log.session
            self.log.extend(
                FeedbackEvent(
                    time=float(times[f]),
                    value=float(values[f]),
                    source=SOURCE,
                    session=board_session(session, f, self.fields),
                )
                for f in due.nonzero().flatten().tolist()
            )
        return values, times

    def state_dict(self) -> dict[str, Any]:
        """Where each field is in the log."""
        return {"next": self.next.clone(), "given": self.given}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        try:
            self.next = state["next"].to(torch.int64).clone()
            self.given = int(state["given"])
        except (KeyError, TypeError, AttributeError) as e:
            raise CheckpointError(f"bad keepaway replay state in the checkpoint ({e!r})") from None
