"""``train.py trainer=interactive`` on Tetris: what the page draws of the game a person watches, and the
person as the game's trainer (each press filed under the placement on screen ``REACTION_S`` before it)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, PlacementTable, placement_table
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.interactive.live import BrowserQueueTrainer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.interactive.timeline import REACTION_S, credit_time
from hfrl_torch.trainers.base import Events

# how long a live game waits after its last placement for feedback on it: the session's reaction allowance
# plus a slow reaction (1 s); LATE_FEEDBACK_S at the default allowance
SLOW_REACTION_S = 1.0
LATE_FEEDBACK_S = REACTION_S + SLOW_REACTION_S


def landing(before: torch.Tensor, piece: int, action: int, table: PlacementTable) -> list[list[int]]:
    """The four ``[row, column]`` cells (row 0 at the bottom) where placement ``action`` of ``piece``
    lands when dropped onto the board ``before`` ([H, W] bool), as the engine drops it."""
    filled = before.to(torch.bool)
    rows = torch.arange(1, filled.shape[0] + 1).view(-1, 1)
    heights = (filled * rows).amax(0).tolist()  # 1 + the highest filled row of each column (0: empty)
    cells = [(int(r), int(c)) for r, c in table.cells[piece, action]]
    lowest: dict[int, int] = {}
    for r, c in cells:
        lowest[c] = min(r, lowest.get(c, r))
    land = max(heights[c] - r for c, r in lowest.items())
    return [[land + r, c] for r, c in cells]


def action_label(td: TensorDictBase, action: int) -> str:
    """Placement ``action`` of the piece in ``td`` in the page's words ("S at column 3, rotation 1")."""
    p = int(td[keys.PIECE][0])
    table = placement_table(td[keys.BOARD].shape[-1])
    column, orient = int(table.column[p, action]), int(table.orient[p, action])
    return f"{PIECE_NAMES[p]} at column {column + 1}, rotation {orient}"


def tetris_frame(td: TensorDictBase, episode: int, weight: float, **extra: Any) -> dict[str, Any]:
    """What the page draws after a placement: the board, the cells just placed, the rows it cleared (with
    the board before they went), the action and its number in the game; ``extra`` is added as is."""
    before = td[keys.BOARD][0]
    after = td["next", keys.BOARD][0]
    p, a = int(td[keys.PIECE][0]), int(td[keys.ACTION][0])
    table = placement_table(before.shape[1])
    cleared = int(td["next", keys.LINES].sum()) - int(td[keys.LINES].sum())
    frame: dict[str, Any] = {
        "type": "tetris",
        "board": after.to(torch.int64).tolist(),
        "placed": [],
        "cleared_rows": [],
        "before_clear": None,
        "cleared": cleared,
        "lines": int(td["next", keys.LINES].sum()),
        "pieces": int(td["next", keys.PIECES_PLACED].sum()),
        "episode": episode,
        "label": f"{PIECE_NAMES[p]} at column {int(table.column[p, a]) + 1}",
        "action": action_label(td, a),
        "weight": weight,
        **extra,
    }
    cells = landing(before, p, a, table)
    if cleared == 0:
        frame["placed"] = cells
    else:
        full = before.clone()
        for r, c in cells:
            if r < full.shape[0]:
                full[r, c] = True
        frame["before_clear"] = full.to(torch.int64).tolist()
        frame["cleared_rows"] = [r for r in range(full.shape[0]) if bool(full[r].all())]
        frame["placed_before_clear"] = cells
    return frame


class BrowserTetrisTrainer(BrowserQueueTrainer):
    """A person in the browser as the trainer of the watched Tetris board.

    Each press is filed under the placement that was on screen ``session.reaction_s`` before it (the
    session's timeline, the same filing the page was told in the press's acknowledgement) and credited on
    the loop's clock at ``min(t_k + r, t_{k+1}, now)``, ``t_k`` the time of that placement and ``t_{k+1}``
    the next one's (``timeline.credit_time``): previous-step credit lands on the placement filed under.

    :param session: the page's session; its queue holds the presses (``human:browser``, wall clock).
    :param log: the feedback log every press goes to, with the time, game and placement it is credited at.
    """

    discrete = True  # a press is credited within its placement (``credit_time``)

    def label(self, event: FeedbackEvent) -> FeedbackEvent:
        """``event`` filed under the placement on screen ``reaction_s`` before it (``session.filed``), at its
        credit time (the placement before its time, as ``QueueTrainer``, where no frame was shown)."""
        seen, later = self.session.filed(event)
        if seen is None:
            return super().label(event).stamped(self.press_session)
        t = credit_time(seen, later, self.session.reaction_s, max(self._now, event.time), discrete=True)
        return FeedbackEvent(
            time=t,
            value=event.value,
            source=event.source,
            step=seen.step,
            episode=seen.episode,
            session=self.press_session,
        )

    def late(self, now: float) -> Events:
        """The presses that came after the game's last placement (``now``: the loop's clock), filed and
        logged; no placement is recorded."""
        self._now = float(now)
        return self._emit([[self.label(ev) for ev in self.queue.drain()]])


class TetrisPage:
    """What the CE learner tells the page: its practice rounds, the games a person watches (each placement
    shown and recorded in the session's timeline), the curve, and what is left of the run.

    A practice round is one CE iteration: the person's game (when a page is open and the person is here),
    then practice on its own (the page's board is covered and presses are not taken), then a test; its
    point on the curve is marked taught when the person watched its game.

    :param session: the page's session.
    :param rounds: the run's practice rounds (``agent.iterations``).
    :param clock: wall clock of the round times (``time.monotonic``).
    """

    def __init__(
        self, session: TeachingSession, rounds: int, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.session = session
        self.rounds = int(rounds)
        self.clock = clock
        self.games = 0
        self._steered = [0, 0]
        self._game_lines: int | None = None  # lines of the watched game in progress (None: none since shown)
        self._round_start: float | None = None
        # the last rounds' wall times, apart for rounds the person watched and rounds that practised alone:
        # a watched round lasts a paced game, one alone a moment, so the time left depends on which come
        self._round_s: dict[bool, list[float]] = {True: [], False: []}
        session.set_live(False)  # nothing to judge before the first game

    def start_game(self, round_index: int) -> None:
        """A game for the person begins (round ``round_index``, 0-based); presses are taken again once its
        first placement is on screen (:meth:`placed`): before it there is nothing to judge, and the first
        one can take seconds (the learner's kernels compile at start-up)."""
        if self._round_start is None:
            self._round_start = self.clock()
        self.games += 1
        self._game_lines = 0
        self._steered = [0, 0]  # placements of this game the teaching changed, and placements
        self._progress(round_index)

    def placed(
        self, td: TensorDictBase, round_index: int, now: float, weight: float, alone: int | None = None
    ) -> None:
        """Show the placement of ``td`` (made at ``now`` on the loop's clock) and record it as what a press
        judges: the session files presses under it. ``alone``: the placement the environment's values alone
        would have chosen, where it is better by them than the one made (the teaching changed the move)."""
        self._steered[1] += 1
        self._steered[0] += alone is not None
        frame = tetris_frame(
            td,
            round_index,
            weight,
            phase="watch",
            game=self.games,
            placement=int(td[keys.PIECES_PLACED].sum()) + 1,
            round=round_index + 1,
            rounds=self.rounds,
            without_you=None if alone is None else action_label(td, alone),
            steered=list(self._steered),
        )
        self.session.publish(frame)
        self._game_lines = int(frame["lines"])
        label = f"{frame['label']} (placement {frame['placement']} of game {self.games})"
        self.session.shown(now, round_index, int(td[keys.PIECES_PLACED].sum()), label)
        if not self.session.live:  # the game's first placement: now there is something to judge
            self.session.set_live(True)

    def practising(self, round_index: int) -> None:
        """Round ``round_index`` practises on its own: nothing to judge on the page."""
        if self._round_start is None:
            self._round_start = self.clock()
        self.session.set_live(False)
        status = {"type": "status", "phase": "practice", "round": round_index + 1, "rounds": self.rounds}
        if self._game_lines is not None:  # the person's game just ended: the page says how it went
            status["game_over"] = {"game": self.games, "lines": self._game_lines}
            self._game_lines = None
        self.session.publish(status)
        self._progress(round_index)

    def point(self, round_index: int, lines: float, taught: bool) -> None:
        """Round ``round_index`` ended with ``lines`` per test game (``taught``: the person watched its
        game)."""
        self.session.add_point(round_index + 1, lines, 1.0 if taught else 0.0)
        now = self.clock()
        if self._round_start is not None:
            self._round_s[taught] = [*self._round_s[taught][-4:], now - self._round_start]
        self._round_start = now
        self._progress(round_index + 1)

    def _progress(self, done: int) -> None:
        """What is left, and how long it takes at the pace of the rounds to come: watched ones while the
        person teaches, practice alone while they are away (None: no such round measured yet)."""
        left = max(self.rounds - done, 0)
        recent = self._round_s[self.session.teaching()]
        per_round = sum(recent) / len(recent) if recent else None
        self.session.set_progress(
            unit="rounds",
            done=done,
            total=self.rounds,
            left=left,
            left_s=None if per_round is None else left * per_round,
        )
