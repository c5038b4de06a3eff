"""A simulated trainer who leaves: ``trainer.leave_after`` episodes, or simulated minutes, of each learner.

Feedback stops there for good; H^ keeps what it learned, and the fusion's weight follows whatever evidence
the learner has from then on. A person leaves the browser page by closing it, so this is for the simulated
trainers and replays.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["LEAVE_UNITS", "Departure"]

LEAVE_UNITS = ("episodes", "minutes")


class Departure:
    """Whether the trainer still watches each learner.

    :param after: episodes or simulated minutes of each learner after which the trainer is gone (None: stays).
    :param unit: ``episodes`` (the learner's finished episodes or games) or ``minutes`` (its simulated clock).
    """

    def __init__(self, after: float | None = None, unit: str = "episodes") -> None:
        if unit not in LEAVE_UNITS:
            raise ValueError(f"leave unit {unit!r} is invalid; allowed: {', '.join(LEAVE_UNITS)}")
        if after is not None and not (math.isfinite(float(after)) and float(after) >= 0):
            raise ValueError(f"leave_after must be None or a number >= 0, got {after!r}")
        self.after = None if after is None else float(after)
        self.unit = unit

    @property
    def leaves(self) -> bool:
        return self.after is not None

    def present(self, episodes: Tensor, seconds: Tensor | float) -> Tensor:
        """Bool, shaped like ``episodes``: the learners whose trainer is still there, given each one's
        finished episodes and simulated clock (seconds)."""
        e = torch.as_tensor(episodes)
        if self.after is None:
            return torch.ones(e.shape, dtype=torch.bool)
        if self.unit == "episodes":
            return e.to(torch.float64) < self.after
        s = torch.as_tensor(seconds, dtype=torch.float64).expand(e.shape)
        return s / 60.0 < self.after

    def present_one(self, episodes: int, seconds: float) -> bool:
        """:meth:`present` of one learner, given its finished episodes and its simulated clock (seconds)."""
        if self.after is None:
            return True
        return (episodes if self.unit == "episodes" else seconds / 60.0) < self.after

    def describe(self) -> str:
        return "stays" if self.after is None else f"leaves after {self.after:g} {self.unit}"

    def __repr__(self) -> str:
        return f"Departure(after={self.after}, unit={self.unit!r})"
