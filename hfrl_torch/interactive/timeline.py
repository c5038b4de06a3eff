"""What the page showed when, and which moment of the game a press is filed under (both domains).

A person reacts some time after what they judge. A press at wall time ``w`` is filed under the frame that
was on screen at ``w - r``, with ``r`` = :data:`REACTION_S` the one reaction allowance of both domains
(0.3 s, near the mode of the thesis's gamma(2.0, 0.28) delay density): the frame the server had sent to the
page that pressed (each page's own sends, so a page that was disconnected or slow is judged by what it
really showed), or without a page the frame published then. It is credited on the game's clock at
``min(S(w - r) + r, end, now)``: ``S(w - r)`` is the game-clock time of that frame, ``now`` the game's clock
when the press is read, and ``end`` (Tetris only) the start of the placement after the one filed under,
because a Tetris step is a whole placement and its credit must not spill into the next one.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass

REACTION_S = 0.3
MIN_REACTION_S, MAX_REACTION_S = 0.05, 2.0  # trainer.reaction_s may be set within these (a calibration)


@dataclass(frozen=True)
class Shown:
    """One frame on the page: when it was shown (wall clock), the game-clock time of what it showed, the
    episode (Tetris: the practice round whose game it was), the step (Tetris: the placement, keepaway: the
    decision; -1: nothing to judge yet) and what a press on it judges, in words ("T at column 9")."""

    wall: float
    sim: float
    episode: int
    step: int
    label: str = ""
    version: int = -1  # the session's frame version it was published as


class ScreenTimeline:
    """The last ``size`` frames the page showed, oldest first (appended in wall-clock order)."""

    def __init__(self, size: int = 1000) -> None:
        if size < 1:
            raise ValueError(f"ScreenTimeline size must be >= 1, got {size!r}")
        self._shown: deque[Shown] = deque(maxlen=size)

    def shown(
        self, wall: float, sim: float, episode: int, step: int, label: str = "", version: int = -1
    ) -> None:
        """Record a frame shown at ``wall`` of the moment ``sim`` on the game's clock."""
        self._shown.append(Shown(float(wall), float(sim), int(episode), int(step), str(label), int(version)))

    def version(self, version: int) -> Shown | None:
        """The frame published as ``version`` (None: not a frame of the game, or no longer kept)."""
        for shown in reversed(self._shown):
            if shown.version == version:
                return shown
            if shown.version < version:
                return None
        return None

    def at(self, wall: float) -> Shown | None:
        """The frame on screen at ``wall``: the last shown at or before it (the oldest kept if ``wall`` is
        older; None if nothing was shown yet)."""
        for shown in reversed(self._shown):
            if shown.wall <= wall:
                return shown
        return self._shown[0] if self._shown else None

    def after(self, frame: Shown) -> Shown | None:
        """The first frame shown after ``frame`` whose step differs from it (None: none yet)."""
        later = None
        for shown in reversed(self._shown):
            if shown.wall <= frame.wall:
                break
            if (shown.episode, shown.step) != (frame.episode, frame.step):
                later = shown
        return later

    def clear(self) -> None:
        """Forget every frame."""
        self._shown.clear()

    def __iter__(self) -> Iterator[Shown]:
        return iter(self._shown)

    def __len__(self) -> int:
        return len(self._shown)


def credit_time(
    seen: Shown | None, later: Shown | None, reaction_s: float, now: float, discrete: bool = False
) -> float:
    """The game-clock time a press filed under ``seen`` is credited at: ``min(seen.sim + r, now)``, and with
    ``discrete`` steps (Tetris placements) before the start of ``later``, the next step (``now`` when
    nothing was shown)."""
    if seen is None:
        return now
    if not discrete:
        return min(seen.sim + reaction_s, now)
    t = seen.sim + max(reaction_s, 1e-3)  # strictly after the step began: previous-step credit lands on it
    if later is not None:
        t = min(t, later.sim)
    return min(t, now)
