"""The trust factor: how much to weigh the person's reward model H^ against the environment (thesis 4.1).

The fusion rules (``argmax_a [R + trust * H^]``, ``argmax_a [R * (1 + H^ ** trust)]``) take it as their
weight. It is the performance-weighted rate at which H^'s best action matches the environment-trained
policy's best action: once from five reference policies (eq. 4.3), then updated every episode (eq. 4.4).
"""

from __future__ import annotations

import math
import numbers
from typing import Any

import torch
from torch import Tensor

from hfrl_torch.common.errors import CheckpointError

__all__ = ["IncrementalTrust", "MatchCounter", "trust_from_policies"]


def _check_rate(m: float, what: str) -> float:
    if isinstance(m, bool) or not isinstance(m, numbers.Real) or not (math.isfinite(m) and 0.0 <= m <= 1.0):
        raise ValueError(f"{what} must be a match rate within [0, 1], got {m!r}")
    return float(m)


def _check_performance(x: float, what: str) -> float:
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not (math.isfinite(x) and x >= 0.0):
        raise ValueError(f"{what} must be a finite performance >= 0 (lines, or hold time), got {x!r}")
    return float(x)


def trust_from_policies(lines: Tensor, match_rates: Tensor) -> float:
    """Thesis eq. 4.3: ``sum(L_i m_i) / sum(L_i)`` over the best environment-only policies P_1..P_5.

    ``lines[i]`` is P_i's performance (lines cleared), ``match_rates[i]`` the fraction of states where the
    person's best action matched P_i's. Any number of policies >= 1 is accepted (the thesis uses five).
    When every ``L_i`` is 0 the weights are undefined; the plain mean of the match rates is returned,
    the limit of equal performances (no policy is more credible than another).
    """
    L = torch.as_tensor(lines, dtype=torch.float64)
    m = torch.as_tensor(match_rates, dtype=torch.float64)
    if L.ndim != 1 or L.numel() == 0 or L.shape != m.shape:
        raise ValueError(
            f"lines and match_rates must be 1-D, same length >= 1, got {tuple(L.shape)} and {tuple(m.shape)}"
        )
    if not (torch.isfinite(L).all() and (L >= 0).all()):
        raise ValueError("lines must be finite and >= 0")
    if not (torch.isfinite(m).all() and (m >= 0).all() and (m <= 1).all()):
        raise ValueError("match_rates must be within [0, 1]")
    total = L.sum()
    if total == 0:
        return float(m.mean())
    return float((L * m).sum() / total)


class IncrementalTrust:
    """Thesis eq. 4.4, once per episode: ``trust_k = (l1 * trust_{k-1} + l2 * m) / (l1 + l2)``.

    ``m`` is the match rate of the last episode (k-1), ``l1`` and ``l2`` the environment performance (lines,
    or hold time in keepaway) of episodes k-2 and k-1. Edge cases, all explicit:

    - first update (no episode k-2): ``l1`` is taken equal to ``l2``, so the prior trust and the first
      episode's evidence weigh the same: ``trust = (trust + m) / 2``;
    - ``l1 + l2 = 0`` (no lines in either episode): the trust is kept; there is no performance to weigh by;
    - ``m is None`` (no H^/policy decisions were compared): the trust is kept.

    In every case the episode's performance becomes the next update's ``l1``.
    """

    def __init__(self, initial: float) -> None:
        if isinstance(initial, bool) or not isinstance(initial, numbers.Real) or not math.isfinite(initial):
            raise ValueError(f"IncrementalTrust initial must be a finite number, got {initial!r}")
        if initial < 0:
            raise ValueError(f"IncrementalTrust initial must be >= 0 (a weight on H^), got {initial!r}")
        self.trust = float(initial)
        self.previous_performance: float | None = None
        self.episodes = 0

    @property
    def value(self) -> float:
        """The current trust factor."""
        return self.trust

    def update(self, performance: float, match_rate: float | None) -> float:
        """Fold in the episode that just ended (performance ``l2``, match rate ``m``).

        Returns the trust for the next episode.
        """
        l2 = _check_performance(performance, "performance")
        m = None if match_rate is None else _check_rate(match_rate, "match_rate")
        l1 = l2 if self.previous_performance is None else self.previous_performance
        if m is not None and l1 + l2 > 0:
            self.trust = (l1 * self.trust + l2 * m) / (l1 + l2)
        self.previous_performance = l2
        self.episodes += 1
        return self.trust

    def state_dict(self) -> dict[str, Any]:
        """Plain Python numbers for a checkpoint (``previous_performance``: None before any update)."""
        return {
            "trust": self.trust,
            "previous_performance": self.previous_performance,
            "episodes": self.episodes,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from ``state_dict()``; a malformed state raises ``CheckpointError``."""
        try:
            trust = float(state["trust"])
            prev = state["previous_performance"]
            prev = None if prev is None else float(prev)
            episodes = int(state["episodes"])
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(
                f"bad IncrementalTrust state ({e!r}); expected keys trust, previous_performance, episodes"
            ) from None
        if not (math.isfinite(trust) and trust >= 0):
            raise CheckpointError(f"bad IncrementalTrust state: trust must be finite and >= 0, got {trust!r}")
        if prev is not None and not (math.isfinite(prev) and prev >= 0):
            raise CheckpointError(f"bad IncrementalTrust state: previous_performance {prev!r} is not >= 0")
        if episodes < 0:
            raise CheckpointError(f"bad IncrementalTrust state: episodes {episodes!r} is negative")
        self.trust, self.previous_performance, self.episodes = trust, prev, episodes


class MatchCounter:
    """Per learner, within its current episode: how often H^'s best action is the environment policy's.

    This is the ``m`` of eqs. 4.3 and 4.4, counted in one place for every learner and domain. A decision
    counts only where H^ prefers some choosable action (an untaught H^, equal everywhere, agrees with
    nothing and disagrees with nothing); best means the first best choosable action (valid, and not
    game-ending unless every valid action ends the game).

    :param learners: L, counted separately.
    """

    def __init__(self, learners: int) -> None:
        if learners < 1:
            raise ValueError(f"MatchCounter needs learners >= 1, got {learners}")
        self.matches = torch.zeros(learners, dtype=torch.int64)
        self.compared = torch.zeros(learners, dtype=torch.int64)

    @property
    def learners(self) -> int:
        return self.matches.shape[0]

    def count(self, env_values: Tensor, human_values: Tensor, choosable: Tensor, learner: Tensor) -> None:
        """Count the decisions of rows ``[M, A]`` (``choosable`` bool ``[M, A]``) made by ``learner`` [M]."""
        h = human_values.detach().to(device="cpu", dtype=torch.float64)
        r = env_values.detach().to(device="cpu", dtype=torch.float64)
        out = ~choosable.detach().cpu().to(torch.bool)
        best = h.masked_fill(out, -torch.inf)
        prefers = best.amax(-1) > h.masked_fill(out, torch.inf).amin(-1)
        same = best.argmax(-1) == r.masked_fill(out, -torch.inf).argmax(-1)
        self.add(learner, (prefers & same).to(torch.int64), prefers.to(torch.int64))

    def add(self, learner: Tensor, matches: Tensor, compared: Tensor) -> None:
        """Add counts made elsewhere (compiled games): ``matches`` and ``compared`` [M] of ``learner`` [M]."""
        idx = learner.detach().cpu().to(torch.int64).reshape(-1)
        self.matches.index_add_(0, idx, matches.detach().cpu().to(torch.int64).reshape(-1))
        self.compared.index_add_(0, idx, compared.detach().cpu().to(torch.int64).reshape(-1))

    def rates(self) -> Tensor:
        """m per learner [L] (float64; NaN where no decision was compared: the trust is then kept)."""
        return torch.where(self.compared > 0, self.matches / self.compared.clamp(min=1), torch.nan).to(
            torch.float64
        )

    def reset(self, learners: Tensor | None = None) -> None:
        """Start new episodes for the flagged learners (bool [L]; None: all)."""
        if learners is None:
            self.matches.zero_()
            self.compared.zero_()
            return
        self.matches[learners] = 0
        self.compared[learners] = 0

    def state_dict(self) -> dict[str, Any]:
        return {"matches": self.matches.clone(), "compared": self.compared.clone()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        try:
            matches, compared = state["matches"].to(torch.int64), state["compared"].to(torch.int64)
        except (KeyError, TypeError, AttributeError) as e:
            raise CheckpointError(
                f"bad MatchCounter state ({e!r}); expected keys matches, compared"
            ) from None
        if matches.shape != self.matches.shape or compared.shape != self.compared.shape:
            raise CheckpointError(
                f"bad MatchCounter state: counts of {matches.numel()} learners, not {self.learners}"
            )
        self.matches, self.compared = matches.clone(), compared.clone()
