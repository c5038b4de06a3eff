"""Weights on H^ over episodes: constant, annealed (Knox & Stone's baseline), trust factor (eqs. 4.3/4.4).

Every fusion rule takes one weight per learner: ``w`` in ``R + w * H^`` (thesis eq. 4.2), the exponent in
``R * (1 + H^ ** w)`` (eq. 5.1), ``beta`` in Knox & Stone's TAMER+RL techniques. A schedule says what that
weight is at a given episode. Schedules are batched over L independent learners (one per board of a
batched env); L = 1 shares one weight among all boards.

Shape rule of :meth:`WeightSchedule.value`: the per-learner parameters are laid along the *first* dimension
of ``episode``. With L = 1 the result has ``episode``'s shape; with L > 1 ``episode`` is either a single
number (every learner at that episode, result ``[L]``) or a tensor whose first dimension is L (result of
``episode``'s shape, e.g. ``[B]`` for one step of a batched env, ``[B, T]`` for a stored rollout).
"""

from __future__ import annotations

import math
import numbers
from abc import ABC, abstractmethod
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.trust import IncrementalTrust

__all__ = [
    "AnnealedWeight",
    "ConstantWeight",
    "SearchedWeight",
    "TrustWeight",
    "WeightSchedule",
    "as_schedule",
]

MatchRateLike = float | None


def _is_number(x: object) -> bool:
    return isinstance(x, numbers.Real) and not isinstance(x, bool)


def _weights(w: float | Sequence[float] | Tensor, what: str) -> Tensor:
    """A 1-D float64 tensor of finite weights >= 0 (a single number becomes ``[1]``)."""
    if _is_number(w):
        t = torch.tensor([float(w)], dtype=torch.float64)
    else:
        try:
            t = torch.as_tensor(w, dtype=torch.float64).detach().cpu().clone()
        except (TypeError, ValueError, RuntimeError):
            raise ValueError(f"{what} must be a number or a 1-D sequence of numbers, got {w!r}") from None
        if t.ndim == 0:
            t = t.reshape(1)
    if t.ndim != 1 or t.numel() == 0:
        raise ValueError(f"{what} must be a number or a non-empty 1-D sequence, got shape {tuple(t.shape)}")
    if not (torch.isfinite(t).all() and (t >= 0).all()):
        raise ValueError(f"{what} must be finite and >= 0 (a weight on H^), got {t.tolist()}")
    return t


def _per_learner(values: Tensor | Sequence[Any] | float | None, learners: int, what: str) -> list[Any]:
    """One entry per learner from a scalar, a sequence or a 1-D tensor (NaN entries become None)."""
    if values is None or _is_number(values):
        return [values] * learners
    if isinstance(values, Tensor):
        if values.ndim == 0:
            return [float(values)] * learners
        values = [None if math.isnan(v) else v for v in values.detach().cpu().double().reshape(-1).tolist()]
    items = list(values)
    if len(items) != learners:
        raise ValueError(f"{what} has {len(items)} entries; expected one per learner ({learners})")
    return items


def _ended(ended: Tensor | Sequence[bool] | None, learners: int) -> Tensor:
    if ended is None:
        return torch.ones(learners, dtype=torch.bool)
    e = torch.as_tensor(ended).detach().cpu()
    if e.dtype != torch.bool or e.shape != (learners,):
        raise ValueError(
            f"ended must be a bool tensor of shape ({learners},), got {e.dtype} {tuple(e.shape)}"
        )
    return e


class WeightSchedule(ABC):
    """The weight on H^ of each of L learners at a given episode.

    Each schedule also counts episodes itself (``episodes``, ``[L]``), advanced by :meth:`end_episode`, for
    callers that do not track the episode index; ``value()`` with no argument uses that count.
    """

    kind: str = ""
    searched: bool = False  # the learner sets the weight by its own search (evidence ``searched``)

    def __init__(self, learners: int) -> None:
        self.learners = int(learners)
        self.episodes = torch.zeros(self.learners, dtype=torch.int64)

    @abstractmethod
    def _parameters_at(self, episode: Tensor) -> Tensor:
        """The per-learner weight ``[L]`` or, laid out by :meth:`_lay`, the weight at ``episode``."""

    def value(self, episode: int | Tensor | None = None) -> Tensor:
        """Weights (float64) at ``episode`` (see the module docstring for the shapes); None: own count."""
        if episode is None:
            e = self.episodes.clone()
        elif _is_number(episode):
            e = torch.tensor(int(episode), dtype=torch.int64)
        else:
            e = torch.as_tensor(episode)
            if e.dtype.is_floating_point or e.dtype == torch.bool:
                raise ValueError(f"episode must be an integer tensor, got {e.dtype}")
        if bool((e < 0).any()):
            raise ValueError(f"episode must be >= 0, got {e.tolist()}")
        return self._parameters_at(e)

    def _lay(self, p: Tensor, e: Tensor) -> Tensor:
        """Per-learner ``p`` [L] broadcast to the shape of ``e`` (learners along its first dimension)."""
        p = p.to(e.device)
        if self.learners == 1:
            return p[0].expand(e.shape).clone()
        if e.ndim == 0:
            return p.clone()
        if e.shape[0] != self.learners:
            raise ValueError(
                f"{type(self).__name__} holds {self.learners} learners but episode has shape "
                f"{tuple(e.shape)}; its first dimension must be {self.learners} (or use one learner)"
            )
        return p.reshape(self.learners, *([1] * (e.ndim - 1))).expand(e.shape).clone()

    def end_episode(
        self,
        performance: float | Sequence[float] | Tensor | None = None,
        match_rate: MatchRateLike | Sequence[MatchRateLike] | Tensor = None,
        ended: Tensor | Sequence[bool] | None = None,
        *,
        compared: Tensor | None = None,
        searched: Tensor | None = None,
    ) -> None:
        """An episode ended for the learners flagged in ``ended`` (bool ``[L]``; None: all of them).

        The evidence each kind of weight reads: ``performance`` (lines, or hold time) and ``match_rate`` (the
        ``m`` of eq. 4.4, None or NaN when no decisions were compared) for the trust factor and the bandit;
        ``compared`` ([L, K, G]: G test games at each of :meth:`compared_weights`' K weights, on the same
        games) for the paired comparison; ``searched`` ([L]: the weight the learner's own search settled
        on) for the searched weight. A schedule ignores what it does not read; every one counts the episode.
        """
        self.episodes += _ended(ended, self.learners).to(torch.int64)

    def compared_weights(self) -> Tensor | None:
        """The weights [K] the learner should play its test games at, on the same games, and pass back as
        ``end_episode(compared=...)``; None: this weight needs no such comparison."""
        return None

    def informed(self) -> bool:
        """Whether the weight rests on the run's own evidence yet (False: a comparison's first arm, played
        before anything was compared); a weight set by a rule or by hand always does."""
        return True

    @abstractmethod
    def describe(self, score: str, episode: str) -> str:
        """What sets the weight, in one or two plain sentences for the teaching page (``score``: what an
        episode is judged by, e.g. "the lines of its games"; ``episode``: "game" or "episode")."""

    def taught(self, taught: Tensor, ended: Tensor | None = None) -> None:  # noqa: B027  (optional hook)
        """Told whether the trainer gave feedback in the flagged learners' episodes that just ended (bool
        [L]); call it before :meth:`end_episode`. Only the bandit uses it."""

    def state_dict(self) -> dict[str, Any]:
        """Plain Python numbers and lists for a checkpoint."""
        return {"kind": self.kind, "episodes": self.episodes.tolist()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore from :meth:`state_dict`; a malformed or foreign state raises ``CheckpointError``."""
        name = type(self).__name__
        try:
            kind = state["kind"]
            episodes = [int(e) for e in state["episodes"]]
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"bad {name} state ({e!r}); expected keys kind, episodes") from None
        if kind != self.kind:
            raise CheckpointError(f"bad {name} state: it is a {kind!r} schedule, not {self.kind!r}")
        if len(episodes) != self.learners or any(e < 0 for e in episodes):
            raise CheckpointError(
                f"bad {name} state: episodes {episodes!r} must be {self.learners} counts >= 0"
            )
        self.episodes = torch.tensor(episodes, dtype=torch.int64)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(learners={self.learners})"


class ConstantWeight(WeightSchedule):
    """A fixed weight: ``w`` at every episode (a number, or one per learner).

    :param w: weight >= 0, or a sequence of L weights.
    """

    kind = "constant"

    def __init__(self, w: float | Sequence[float] | Tensor) -> None:
        weight = _weights(w, "ConstantWeight w")
        super().__init__(weight.numel())
        self.weight = weight

    def _parameters_at(self, episode: Tensor) -> Tensor:
        return self._lay(self.weight, episode)

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "weight": self.weight.tolist()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        try:
            weight = _weights(state["weight"], "weight")
        except (KeyError, ValueError) as e:
            raise CheckpointError(f"bad ConstantWeight state: {e}") from None
        if weight.numel() != self.learners:
            raise CheckpointError(
                f"bad ConstantWeight state: {weight.numel()} weights, expected {self.learners}"
            )
        self.weight = weight

    def describe(self, score: str, episode: str) -> str:
        values = sorted(set(self.weight.tolist()))
        shown = f"={values[0]:g}" if len(values) == 1 else ""
        return f"w is fixed for this run (fusion.weight{shown}): it does not change."

    def __repr__(self) -> str:
        return f"ConstantWeight({self.weight.tolist()})"


class AnnealedWeight(WeightSchedule):
    """Knox & Stone's annealed weight, the thesis's Figure 4.1 baseline ([6]): ``w0 * factor**episode``.

    Knox's code multiplies beta by 0.98 at the end of every episode, so episode k (counted from 0) uses
    ``beta0 * 0.98**k``; as H^ is trusted less over time, the environment takes over.

    :param w0: the weight of episode 0 (>= 0), or one per learner.
    :param factor: the annealing factor per episode, in (0, 1].
    """

    kind = "annealed"

    def __init__(self, w0: float | Sequence[float] | Tensor, factor: float = 0.98) -> None:
        weight = _weights(w0, "AnnealedWeight w0")
        if not (_is_number(factor) and 0.0 < factor <= 1.0):
            raise ValueError(f"AnnealedWeight factor must be a number in (0, 1], got {factor!r}")
        super().__init__(weight.numel())
        self.w0 = weight
        self.factor = float(factor)

    def _parameters_at(self, episode: Tensor) -> Tensor:
        w0 = self._lay(self.w0, episode)
        return w0 * torch.pow(torch.tensor(self.factor, dtype=torch.float64), episode.to(torch.float64))

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "w0": self.w0.tolist(), "factor": self.factor}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        try:
            w0 = _weights(state["w0"], "w0")
            factor = float(state["factor"])
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"bad AnnealedWeight state: {e}") from None
        if w0.numel() != self.learners or not 0.0 < factor <= 1.0:
            raise CheckpointError(
                f"bad AnnealedWeight state: w0 {w0.tolist()} (expected {self.learners} values), "
                f"factor {factor!r} (expected (0, 1])"
            )
        self.w0, self.factor = w0, factor

    def describe(self, score: str, episode: str) -> str:
        start = sorted(set(self.w0.tolist()))
        began = f"started at {start[0]:g}" if len(start) == 1 else "started at its first value"
        return (
            f"w {began} and shrinks by a factor {self.factor:g} after every {episode} "
            "(Knox & Stone's annealing), whatever you press."
        )

    def __repr__(self) -> str:
        return f"AnnealedWeight(w0={self.w0.tolist()}, factor={self.factor})"


class TrustWeight(WeightSchedule):
    """The trust factor as the weight (thesis 4.1): eq. 4.3 gives its start, eq. 4.4 updates it per episode.

    Each learner has its own :class:`IncrementalTrust`, held (not copied): :meth:`end_episode` folds the
    episode's performance ``l2`` and match rate ``m`` into it, so the trust objects passed in see the
    updates. The weight at any episode is the current trust; ``episode`` only gives the result's shape (a
    trust factor is a running state, not a function of the episode index).

    :param trust: one ``IncrementalTrust``, or one per learner.
    """

    kind = "trust"

    def __init__(self, trust: IncrementalTrust | Sequence[IncrementalTrust]) -> None:
        trusts = [trust] if isinstance(trust, IncrementalTrust) else list(trust)
        if not trusts or not all(isinstance(t, IncrementalTrust) for t in trusts):
            raise ValueError("TrustWeight needs an IncrementalTrust or a non-empty sequence of them")
        super().__init__(len(trusts))
        self.trusts = trusts

    @classmethod
    def from_initial(cls, initial: float | Sequence[float], learners: int = 1) -> TrustWeight:
        """L fresh learners starting at ``initial`` (e.g. eq. 4.3's ``trust_from_policies``), or one each."""
        start = _weights(initial, "TrustWeight initial")
        if start.numel() == 1:
            start = start.expand(learners)
        elif start.numel() != learners:
            raise ValueError(f"TrustWeight initial has {start.numel()} values for {learners} learners")
        return cls([IncrementalTrust(float(t)) for t in start])

    def _parameters_at(self, episode: Tensor) -> Tensor:
        return self._lay(torch.tensor([t.value for t in self.trusts], dtype=torch.float64), episode)

    def end_episode(
        self,
        performance: float | Sequence[float] | Tensor | None = None,
        match_rate: MatchRateLike | Sequence[MatchRateLike] | Tensor = None,
        ended: Tensor | Sequence[bool] | None = None,
        *,
        compared: Tensor | None = None,
        searched: Tensor | None = None,
    ) -> None:
        """Eq. 4.4 for each flagged learner: ``trust = (l1 * trust + l2 * m) / (l1 + l2)``.

        ``match_rate`` entries may be numbers, None (no decision compared: trust kept) or NaN in a tensor
        (same as None), e.g. :meth:`~hfrl_torch.fusion.trust.MatchCounter.rates`.
        """
        if performance is None:
            raise ValueError("TrustWeight.end_episode needs the episode's performance (lines, or hold time)")
        flags = _ended(ended, self.learners)
        perf = _per_learner(performance, self.learners, "performance")
        rates = _per_learner(match_rate, self.learners, "match_rate")
        for i in flags.nonzero().flatten().tolist():
            m = rates[i]
            self.trusts[i].update(perf[i], None if m is None else float(m))
        super().end_episode(ended=flags)

    def state_dict(self) -> dict[str, Any]:
        return {**super().state_dict(), "trusts": [t.state_dict() for t in self.trusts]}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        trusts = state.get("trusts")
        if not isinstance(trusts, list) or len(trusts) != self.learners:
            raise CheckpointError(f"bad TrustWeight state: 'trusts' must be a list of {self.learners} states")
        for t, s in zip(self.trusts, trusts, strict=True):
            t.load_state_dict(s)

    def describe(self, score: str, episode: str) -> str:
        return (
            "w is the trust factor (thesis eq. 4.4): how often the move the agent's model of your presses "
            f"rates best matches the move its own value rates best, weighted by {score}. It measures that "
            f"agreement, not you, and changes after every {episode} with or without presses."
        )

    def __repr__(self) -> str:
        return f"TrustWeight({[t.value for t in self.trusts]})"


class SearchedWeight(ConstantWeight):
    """A weight the learner's own search sets: CE's ``fusion.weight=adaptive`` samples it as one more
    dimension of its Gaussian, so the games' scores select it with the value function's weights. The
    schedule holds the weight of the current mean policy (:meth:`set`); episodes do not move it.

    :param w: the weight before the first search step (>= 0), or one per learner.
    """

    kind = "search"
    searched = True

    def end_episode(
        self,
        performance: float | Sequence[float] | Tensor | None = None,
        match_rate: MatchRateLike | Sequence[MatchRateLike] | Tensor = None,
        ended: Tensor | Sequence[bool] | None = None,
        *,
        compared: Tensor | None = None,
        searched: Tensor | None = None,
    ) -> None:
        """The learner's search settled on ``searched`` [L] (None: the weight is kept)."""
        if searched is not None:
            self.set(searched)
        super().end_episode(ended=ended)

    def set(self, w: float | Sequence[float] | Tensor) -> None:
        """The searched weight of each learner from now on (clamped at 0: a negative weight is no H^)."""
        value = torch.as_tensor(w, dtype=torch.float64).detach().cpu().reshape(-1).clamp(min=0.0)
        self.weight = _weights(value.expand(self.learners).clone(), "SearchedWeight w")

    def describe(self, score: str, episode: str) -> str:
        return (
            "w is searched by the cross-entropy method as one more setting (fusion.weight=search): each "
            "practice round keeps the weights whose games scored best. It measures how much your "
            "teaching helps the score, not you."
        )

    def __repr__(self) -> str:
        return f"SearchedWeight({self.weight.tolist()})"


def as_schedule(weight: float | Sequence[float] | Tensor | WeightSchedule) -> WeightSchedule:
    """A schedule as given, or a :class:`ConstantWeight` of a number (or of one number per learner)."""
    if isinstance(weight, WeightSchedule):
        return weight
    return ConstantWeight(weight)
