"""A weight on H^ chosen by the environment's own evidence: discounted Thompson sampling over weights.

``fusion.weight=bandit`` (and ``adaptive`` for every learner but CE): each learner plays each episode at one
weight of ``arms`` and scores it by the episode's performance (lines, or hold time); the next episode's weight
is the arm whose sampled mean score is highest. The score is ``log(1 + performance)``: Tetris lines and
keepaway hold times are skewed and multiplicative (a policy twice as good scores a constant more), so the log
makes arms' noise comparable. Evidence is discounted by ``discount`` per episode of the learner (Raj &
Kalyani 2017, "Taming non-stationary bandits"), so arms not played lately grow uncertain and are tried again:
the weight follows a trainer who leaves (H^ frozen while Q improves) or an H^ that gets better or worse.

The model of each arm's mean is Gaussian, shrunk towards a prior by ``prior_count`` pseudo-episodes, with the
learner's pooled residual variance (a known-variance Thompson sampler with an empirical-Bayes prior). The
prior is the learner's pooled mean, raised by ``prior_trust`` for the highest weight while the trainer
teaches (gave feedback in the learner's last episode): a learner trusts its teacher until the returns say
otherwise, as the thesis's agents do (their trust starts from eq. 4.3), and the first episode plays the
highest weight. The trust is worth more than a tie-break: TAMER's H^ learns best from feedback on its own
choices, so an H^ that is not followed while the trainer is there is taught on another policy's states and
looks worse than it would be. Once the trainer is gone that reason is gone too, and the prior is the pooled
mean alone. Evidence decays, the prior does not, so an arm long unplayed returns to its prior and is tried
again.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.schedules import WeightSchedule, _ended, _per_learner, _weights

__all__ = ["DEFAULT_ARMS", "BanditWeight"]

DEFAULT_ARMS = (0.0, 1.0, 16.0)  # no H^, an equal say, H^ decides
PRIOR_VARIANCE = 0.25  # of a score (log scale) before any evidence: a factor of about e^0.5 either way
MIN_VARIANCE = 0.01  # the pooled variance's floor, so one lucky streak cannot make an arm certain


class BanditWeight(WeightSchedule):
    """Per learner, the weight of its current episode: one of ``arms``, by discounted Thompson sampling.

    :param learners: L, each with its own evidence and draws.
    :param arms: the weights to choose from (>= 0, at least two).
    :param discount: evidence kept per episode of the learner, in (0, 1] (1: stationary).
    :param prior_count: pseudo-episodes of the prior each arm's mean is shrunk towards (> 0).
    :param prior_trust: how much better (in score, log(1 + performance)) the highest weight is believed to be
        before any evidence (>= 0).
    :param seed: seed of the draws.
    """

    kind = "bandit"

    def __init__(
        self,
        learners: int,
        arms: Sequence[float] | Tensor = DEFAULT_ARMS,
        discount: float = 0.99,
        prior_count: float = 4.0,
        prior_trust: float = 0.5,
        seed: int = 0,
    ) -> None:
        super().__init__(learners)
        grid = _weights(arms, "bandit arms")
        if grid.numel() < 2:
            raise ValueError(f"bandit arms must hold at least two weights, got {grid.tolist()}")
        if not (0.0 < float(discount) <= 1.0):
            raise ValueError(f"bandit discount must be in (0, 1], got {discount!r}")
        if not (math.isfinite(float(prior_count)) and float(prior_count) > 0.0):
            raise ValueError(f"bandit prior_count must be > 0, got {prior_count!r}")
        if not (math.isfinite(float(prior_trust)) and float(prior_trust) >= 0.0):
            raise ValueError(f"bandit prior_trust must be >= 0, got {prior_trust!r}")
        self.arms = grid
        self.discount, self.prior_count = float(discount), float(prior_count)
        self.prior_trust = float(prior_trust)
        shape = (self.learners, grid.numel())
        self.count = torch.zeros(shape, dtype=torch.float64)  # discounted episodes per arm
        self.total = torch.zeros(shape, dtype=torch.float64)  # discounted sum of scores
        self.square = torch.zeros(shape, dtype=torch.float64)  # discounted sum of squared scores
        self.arm = torch.full((self.learners,), int(grid.argmax()), dtype=torch.int64)
        self.teaching = torch.ones(self.learners, dtype=torch.bool)  # the trainer taught the last episode
        self.generator = torch.Generator().manual_seed(int(seed))

    def _parameters_at(self, episode: Tensor) -> Tensor:
        return self._lay(self.arms[self.arm], episode)

    @staticmethod
    def score(performance: Tensor) -> Tensor:
        """What an episode is judged by: ``log(1 + performance)``."""
        return torch.log1p(performance.to(torch.float64).clamp(min=0.0))

    def posterior(self) -> tuple[Tensor, Tensor]:
        """Mean and variance [L, K] of each arm's mean score, given the evidence so far."""
        n = self.count.sum(-1, keepdim=True)
        pooled = torch.where(n > 0, self.total.sum(-1, keepdim=True) / n.clamp(min=1e-12), 0.0)
        # pooled residual variance about each arm's own mean, with PRIOR_VARIANCE as one pseudo-episode
        arm_mean = self.total / self.count.clamp(min=1e-12)
        residual = (self.square - self.count * arm_mean**2).clamp(min=0.0).sum(-1, keepdim=True)
        variance = ((residual + PRIOR_VARIANCE) / (n + 1.0)).clamp(min=MIN_VARIANCE)
        top = (self.arms == self.arms.max()).to(torch.float64)
        prior = pooled + self.prior_trust * self.teaching.to(torch.float64).unsqueeze(-1) * top
        weight = self.count + self.prior_count
        mean = (self.total + self.prior_count * prior) / weight
        return mean, variance / weight

    def taught(self, taught: Tensor, ended: Tensor | None = None) -> None:
        """Whether the trainer gave feedback in the flagged learners' last episodes (the prior trusts H^ only
        while it does)."""
        flags = _ended(ended, self.learners)
        t = torch.as_tensor(taught).detach().cpu().to(torch.bool).reshape(-1).expand(self.learners)
        self.teaching = torch.where(flags, t, self.teaching)

    def end_episode(
        self,
        performance: float | Sequence[float] | Tensor | None = None,
        match_rate: Any = None,
        ended: Tensor | Sequence[bool] | None = None,
        *,
        compared: Tensor | None = None,
        searched: Tensor | None = None,
    ) -> None:
        """Score the flagged learners' episodes at their current arms, discount, and draw their next arms."""
        if performance is None:
            raise ValueError("BanditWeight.end_episode needs the episode's performance (lines, or hold time)")
        flags = _ended(ended, self.learners)
        perf = torch.tensor([float(p) for p in _per_learner(performance, self.learners, "performance")])
        if not bool(torch.isfinite(perf[flags]).all()):
            raise ValueError(f"bandit performance must be finite, got {perf[flags].tolist()}")
        rows = flags.nonzero().flatten()
        if rows.numel():
            y = self.score(perf[rows])
            keep = torch.full((rows.numel(), 1), self.discount, dtype=torch.float64)
            self.count[rows] *= keep
            self.total[rows] *= keep
            self.square[rows] *= keep
            arm = self.arm[rows]
            self.count[rows, arm] += 1.0
            self.total[rows, arm] += y
            self.square[rows, arm] += y * y
            mean, variance = self.posterior()
            draw = torch.randn(mean.shape, generator=self.generator, dtype=torch.float64)
            sampled = mean + variance.sqrt() * draw  # every learner draws, so draws do not depend on flags
            self.arm[rows] = sampled[rows].argmax(-1)
        super().end_episode(ended=flags)

    def probabilities(self, draws: int = 1000) -> Tensor:
        """Each arm's chance [L, K] of being drawn next (a Monte Carlo estimate, for the logs and tests)."""
        mean, variance = self.posterior()
        g = torch.Generator().manual_seed(0)
        sampled = mean + variance.sqrt() * torch.randn((draws, *mean.shape), generator=g, dtype=torch.float64)
        best = sampled.argmax(-1)
        return torch.nn.functional.one_hot(best, self.arms.numel()).to(torch.float64).mean(0)

    def state_dict(self) -> dict[str, Any]:
        return {
            **super().state_dict(),
            "arms": self.arms.tolist(),
            "discount": self.discount,
            "prior_count": self.prior_count,
            "prior_trust": self.prior_trust,
            "count": self.count.clone(),
            "total": self.total.clone(),
            "square": self.square.clone(),
            "arm": self.arm.clone(),
            "teaching": self.teaching.clone(),
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        try:
            arms = _weights(state["arms"], "arms")
            stats = [state[k].to(torch.float64) for k in ("count", "total", "square")]
            arm = state["arm"].to(torch.int64)
            teaching = state["teaching"].to(torch.bool)
            self.generator.set_state(state["generator"])
            discount, prior_count = float(state["discount"]), float(state["prior_count"])
            prior_trust = float(state["prior_trust"])
        except (KeyError, TypeError, AttributeError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"bad BanditWeight state ({e!r})") from None
        if arms.tolist() != self.arms.tolist():
            raise CheckpointError(
                f"bad BanditWeight state: arms {arms.tolist()}, this run has {self.arms.tolist()}"
            )
        same = arm.shape == teaching.shape == self.arm.shape
        if any(s.shape != self.count.shape for s in stats) or not same:
            raise CheckpointError("bad BanditWeight state: evidence of another number of learners or arms")
        if bool(((arm < 0) | (arm >= arms.numel())).any()):
            raise CheckpointError(f"bad BanditWeight state: arm indices {arm.tolist()} out of range")
        self.count, self.total, self.square = (s.clone() for s in stats)
        self.arm, self.discount, self.prior_count = arm.clone(), discount, prior_count
        self.prior_trust, self.teaching = prior_trust, teaching.clone()

    def describe(self, score: str, episode: str) -> str:
        arms = ", ".join(f"{a:g}" for a in self.arms.tolist())
        return (
            f"w is chosen among {arms} by a bandit (fusion.weight=adaptive) that favours the weight whose "
            f"recent {episode}s went best, judged on {score}. It measures how much your teaching helps, "
            "not you."
        )

    def __repr__(self) -> str:
        return f"BanditWeight(arms={self.arms.tolist()}, discount={self.discount}, learners={self.learners})"
