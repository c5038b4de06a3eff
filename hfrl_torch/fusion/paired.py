"""CE's adaptive weight on H^: the weights compared on the same test games, every iteration.

``fusion.weight=adaptive`` with ``agent=cem`` and a decision-level scheme: after each CE step the mean
policy plays its test games once at every weight of ``fusion.adaptive.paired_arms``, on the same games
(common random numbers), and the next iteration plays at the weight whose games scored best. The evidence is
paired, so a few dozen games tell the weights apart where single episodes could not; it is fresh, because it
judges H^ together with the current value weights; and it costs no episode of the learner, only test games.
Scores (``log(1 + lines)`` averaged over the games) are smoothed over iterations by ``discount`` so that one
unlucky set of games does not swing the weight.

The arms stop at an equal say (the default is 0, 0.25, 1 on the common [0, 1] scale of R and H^): a
population that plays where H^ outvotes R is ranked by H^'s choices, so R's weights would feel no selection
and stay where they are, and the weight would then stay high for want of a better R. Measured as
``fusion.weight=search`` (the weight as one more dimension of CE's Gaussian), that trap is what happened.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.schedules import WeightSchedule, _weights

__all__ = ["DEFAULT_PAIRED_ARMS", "PairedWeight"]

DEFAULT_PAIRED_ARMS = (0.0, 0.25, 1.0)  # no H^, a tie-breaker, an equal say


class PairedWeight(WeightSchedule):
    """The weight each learner plays at: the arm whose paired test games scored best so far.

    :param learners: L (CE runs one).
    :param arms: the weights compared (>= 0, at least two).
    :param discount: weight of the earlier iterations' scores against the latest, in [0, 1) (0: the latest
        comparison alone).
    :param first: the arm played before any comparison (an index into ``arms``).
    """

    kind = "paired"

    def __init__(
        self,
        learners: int,
        arms: Sequence[float] | Tensor = DEFAULT_PAIRED_ARMS,
        discount: float = 0.5,
        first: int | None = None,
    ) -> None:
        super().__init__(learners)
        grid = _weights(arms, "paired arms")
        if grid.numel() < 2:
            raise ValueError(f"paired arms must hold at least two weights, got {grid.tolist()}")
        if not 0.0 <= float(discount) < 1.0:
            raise ValueError(f"paired discount must be in [0, 1), got {discount!r}")
        start = int(grid.argmax()) if first is None else int(first)
        if not 0 <= start < grid.numel():
            raise ValueError(f"paired first arm {first!r} is not an index of {grid.tolist()}")
        self.arms, self.discount = grid, float(discount)
        self.scores = torch.full((self.learners, grid.numel()), torch.nan, dtype=torch.float64)
        self.arm = torch.full((self.learners,), start, dtype=torch.int64)

    def _parameters_at(self, episode: Tensor) -> Tensor:
        return self._lay(self.arms[self.arm], episode)

    def compared_weights(self) -> Tensor:
        return self.arms.clone()

    def informed(self) -> bool:
        return not bool(self.scores.isnan().all())

    def end_episode(
        self,
        performance: float | Sequence[float] | Tensor | None = None,
        match_rate: Any = None,
        ended: Tensor | Sequence[bool] | None = None,
        *,
        compared: Tensor | None = None,
        searched: Tensor | None = None,
    ) -> None:
        """Fold in ``compared`` ([L, K, G], the test games at every arm; None: no comparison this time) and
        count the episode."""
        if compared is not None:
            self.compare(compared)
        super().end_episode(ended=ended)

    @staticmethod
    def score(lines: Tensor) -> Tensor:
        """What a set of test games scores: the mean of ``log(1 + lines)`` over its last dimension."""
        return torch.log1p(lines.to(torch.float64).clamp(min=0.0)).mean(-1)

    def compare(self, lines: Tensor) -> Tensor:
        """Fold in one comparison: ``lines`` [L, K, G] (or [K, G] for one learner), the G test games played
        at each of the K arms on the same games; returns the arm each learner plays next."""
        x = lines.reshape(self.learners, self.arms.numel(), -1)
        latest = self.score(x)
        smoothed = self.discount * self.scores + (1 - self.discount) * latest
        kept = torch.where(self.scores.isnan(), latest, smoothed)
        self.scores = kept
        self.arm = kept.argmax(-1)
        return self.arm.clone()

    def state_dict(self) -> dict[str, Any]:
        return {
            **super().state_dict(),
            "arms": self.arms.tolist(),
            "discount": self.discount,
            "scores": self.scores.clone(),
            "arm": self.arm.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        try:
            arms = _weights(state["arms"], "arms")
            scores, arm = state["scores"].to(torch.float64), state["arm"].to(torch.int64)
            discount = float(state["discount"])
        except (KeyError, TypeError, AttributeError, ValueError) as e:
            raise CheckpointError(f"bad PairedWeight state ({e!r})") from None
        if arms.tolist() != self.arms.tolist():
            raise CheckpointError(
                f"bad PairedWeight state: arms {arms.tolist()}, this run has {self.arms.tolist()}"
            )
        if scores.shape != self.scores.shape or arm.shape != self.arm.shape:
            raise CheckpointError("bad PairedWeight state: scores of another number of learners or arms")
        if bool(((arm < 0) | (arm >= arms.numel())).any()):
            raise CheckpointError(f"bad PairedWeight state: arm indices {arm.tolist()} out of range")
        self.scores, self.arm, self.discount = scores.clone(), arm.clone(), discount

    def describe(self, score: str, episode: str) -> str:
        arms = ", ".join(f"{a:g}" for a in self.arms.tolist())
        return (
            f"w is chosen among {arms} (fusion.weight=adaptive): after each practice round the agent plays "
            f"the same test {episode}s at every one of these weights and keeps the weight whose {episode}s "
            f"scored best, judged on {score}. It measures how much your teaching helps the score, not you."
        )

    def __repr__(self) -> str:
        return f"PairedWeight(arms={self.arms.tolist()}, discount={self.discount})"
