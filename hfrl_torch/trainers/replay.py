"""Replay of a recorded feedback log on a new run (what a trainer gave in an earlier session).

Matching rule: a recorded event with ``episode`` e and ``step`` s is given at the new run's placement s
of game e on the same board, with its recorded value, stamped ``time + reaction`` of that new placement
(so ``PreviousStep`` credit lands on that placement); events of steps the new run never reaches (its
games are shorter) are not given. A log of a batched run labels each board's events with the session
``"<session>/board<b>"`` (``base.board_session``); those go to board b only. Events of a one-board session
go to every board. Events without a step or episode (-1) cannot be matched and are skipped (counted in
``unmatched``).
"""

from __future__ import annotations

import os
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import replace

import torch
from tensordict import TensorDictBase

from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.trainers.base import Events, Trainer, all_active, board_of, placement_steps


class ReplayTrainer(Trainer):
    """Gives the events of a recorded log again, matched by (board, episode, step); source ``"replay"``.

    :param events: the recorded events (e.g. ``load_feedback_log(path)``).
    :param reaction: seconds between the new placement and the replayed event (> 0).
    :param log: feedback log every replayed event is appended to.
    """

    source = "replay"

    def __init__(
        self, events: Iterable[FeedbackEvent], reaction: float = 0.3, log: FeedbackLog | None = None
    ) -> None:
        super().__init__(log)
        if not reaction > 0:
            raise ValueError(f"ReplayTrainer reaction must be > 0 seconds, got {reaction!r}")
        self.reaction = float(reaction)
        self.unmatched = 0
        self._by_step: dict[tuple[int | None, int, int], list[FeedbackEvent]] = defaultdict(list)
        for ev in events:
            if ev.step < 0 or ev.episode < 0:
                self.unmatched += 1
                continue
            self._by_step[(board_of(ev.session), ev.episode, ev.step)].append(ev)

    @classmethod
    def from_log(cls, path: str | os.PathLike[str], **kwargs: object) -> ReplayTrainer:
        """A replay of the feedback log at ``path`` (every session in it)."""
        return cls(load_feedback_log(path), **kwargs)  # type: ignore[arg-type]

    def give(
        self,
        obs: TensorDictBase,
        action: torch.Tensor,
        time: float,
        episode: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> Events:
        act = all_active(obs, active)
        steps = placement_steps(obs)
        events: Events = []
        for i in range(act.shape[0]):
            if not act[i]:
                events.append([])
                continue
            e, s = int(episode[i]), int(steps[i])
            recorded = self._by_step.get((i, e, s), []) + self._by_step.get((None, e, s), [])
            events.append(
                [
                    replace(ev, time=time + self.reaction, source=self.source, session="", step=s, episode=e)
                    for ev in recorded
                ]
            )
        return self._emit(events)
