"""The interface every trainer implements, simulated or not, and what they share (logging, board labels).

A trainer watches a batch of B boards. Once per step, before the placement is applied, the training loop
calls ``give(obs, action, time, episode, active)`` and gets back, for each board, the list of feedback
events (usually none or one) the trainer gives on that placement. The loop hands them to the agent,
whose credit model assigns each event to steps by its ``time``. At the end of every game the loop calls
``end_games`` so that trainers whose behaviour depends on the agent's results can see them.

Times are seconds on the loop's clock: the placement of a step happens at ``time``; a trainer reacts
after it, so every event it gives is stamped ``time + reaction`` (a fixed ``reaction`` > 0, or a random
delay drawn by ``timing.HumanLikeTiming``). Events carry the ``episode`` (game of that board, 0-based)
and ``step`` (placement within the game, 0-based) they judge.
"""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from typing import Any

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog

Events = list[list[FeedbackEvent]]  # one list of events per board

_BOARD_SUFFIX = re.compile(r"^(?P<session>.*)/board(?P<board>\d+)$")


def board_session(session: str, board: int, boards: int) -> str:
    """The session label of board ``board``'s events: the session itself for one board, else
    ``"<session>/board<b>"``, so that a log of a batched run can be split by board again."""
    return session if boards == 1 else f"{session}/board{board}"


def board_of(session: str) -> int | None:
    """The board a session label names (``"<session>/board<b>"``), or None for a one-board session."""
    m = _BOARD_SUFFIX.match(session)
    return int(m.group("board")) if m else None


class Trainer(ABC):
    """Gives feedback on the agent's placements, one list of ``FeedbackEvent`` per board.

    :param log: a ``FeedbackLog`` every given event is appended to (None = no log). When a trainer wraps
        another, pass the log to the outer one only.
    """

    source: str = "trainer"

    def __init__(self, log: FeedbackLog | None = None) -> None:
        self.log = log
        self.given = 0

    @abstractmethod
    def give(
        self,
        obs: TensorDictBase,
        action: torch.Tensor,
        time: float,
        episode: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> Events:
        """Feedback on placing ``action`` [B] on the boards of ``obs`` (the observation before the
        placement), which happens at ``time`` seconds; ``episode`` [B] is each board's game index and
        ``active`` [B] (default all) the boards whose learners are still training (no feedback elsewhere)."""

    def end_games(self, done: torch.Tensor, lines: torch.Tensor) -> None:  # noqa: B027  (optional hook)
        """Told that the games of the boards where ``done`` [B] is set ended with ``lines`` [B] lines."""

    def state_dict(self) -> dict[str, Any]:
        """What a resumed run needs to continue this trainer as if never stopped: its generator's state, its
        count, and the state of the trainer it wraps (if any)."""
        state: dict[str, Any] = {"given": self.given}
        generator = getattr(self, "generator", None)
        if isinstance(generator, torch.Generator):
            state["generator"] = generator.get_state()
        inner = getattr(self, "trainer", None)
        if isinstance(inner, Trainer):
            state["inner"] = inner.state_dict()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; another kind of trainer's state raises ``CheckpointError``."""
        try:
            self.given = int(state["given"])
            generator = getattr(self, "generator", None)
            if isinstance(generator, torch.Generator):
                generator.set_state(state["generator"])
            inner = getattr(self, "trainer", None)
            if isinstance(inner, Trainer):
                inner.load_state_dict(state["inner"])
        except (KeyError, TypeError, ValueError, RuntimeError) as e:
            raise CheckpointError(f"bad {type(self).__name__} state in the checkpoint ({e!r})") from None

    def _one_per_board(
        self,
        values: torch.Tensor,
        give: torch.Tensor,
        time: float,
        obs: TensorDictBase,
        episode: torch.Tensor,
    ) -> Events:
        """One event valued ``values[b]`` at ``time`` on each board b where ``give[b]``, then logged."""
        steps = placement_steps(obs).tolist()
        value, games = values.reshape(-1).tolist(), episode.reshape(-1).to(torch.int64).tolist()
        events: Events = [
            [
                FeedbackEvent(
                    time=time, value=float(value[i]), source=self.source, step=steps[i], episode=games[i]
                )
            ]
            if g
            else []
            for i, g in enumerate(give.reshape(-1).tolist())
        ]
        return self._emit(events)

    def _emit(self, events: Events) -> Events:
        """Append every event to the log (each board's under its own session label), all boards' with one
        write and one fsync, and count them."""
        counts = [len(e) for e in events]
        self.given += sum(counts)
        if self.log is None or not any(counts):
            return events
        boards = len(events)
        stamped = [
            e if e.session else e.stamped(board_session(self.log.session, b, boards))
            for b, evs in enumerate(events)
            for e in evs
        ]
        written = iter(self.log.extend(stamped))
        return [[next(written) for _ in range(n)] for n in counts]


def placement_steps(obs: TensorDictBase) -> torch.Tensor:
    """Index [B] of the step about to be taken within each board's episode (0-based): Tetris's placements,
    else TorchRL's ``StepCounter`` count, else -1 (not known) on a task that counts neither."""
    for key in (keys.PIECES_PLACED, keys.STEP_COUNT):
        steps = obs.get(key, None)
        if steps is not None:
            return steps.reshape(-1).to(torch.int64)
    return torch.full((obs.batch_size.numel(),), -1, dtype=torch.int64)


def all_active(obs: TensorDictBase, active: torch.Tensor | None) -> torch.Tensor:
    """``active`` as a bool [B] tensor (all True when None)."""
    b = obs.batch_size[0]
    return torch.ones(b, dtype=torch.bool) if active is None else active.reshape(b).to(torch.bool).cpu()
