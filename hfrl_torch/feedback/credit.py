"""Credit assignment for delayed human feedback (TAMER; thesis section 5, Figure 5.5).

A person reacts 0.2-1 s after the event they judge. A feedback ``h`` given at wall-clock time ``t`` is
spread over the steps before it: step ``i``, which lasted ``[t_i, t_{i+1})``, gets the credit

    c_i = integral of f over [t - t_{i+1}, t - t_i]

where ``f`` is the density of the person's reaction delay (Knox & Stone, K-CAP 2009; the thesis uses
gamma(shape 2.0, scale 0.28) over a 500 ms window). The integrals are exact differences of the CDF.

Every time here is seconds on one clock. Times are converted to float64 before anything is subtracted:
wall-clock seconds (~1.7e9) have a resolution of about two minutes in float32.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod

import torch
from torch import Tensor

__all__ = [
    "CREDITS",
    "CreditModel",
    "DelayDensity",
    "GammaDelay",
    "PreviousStep",
    "UniformDelay",
    "credit_weights",
]

CREDITS = ("previous_step", "gamma", "uniform")  # human.credit: PreviousStep, GammaDelay, UniformDelay


class DelayDensity(ABC):
    """Density ``f`` of the delay between an event and the person's feedback on it; ``f(x) = 0`` for x < 0."""

    @abstractmethod
    def cdf(self, x: Tensor) -> Tensor:
        """P(delay <= x), elementwise; 0 for x <= 0."""

    def mass(self, lo: Tensor, hi: Tensor) -> Tensor:
        """Integral of ``f`` over ``[lo, hi]`` (0 where hi <= lo), exact from the CDF."""
        return (self.cdf(hi) - self.cdf(lo)).clamp_min(0.0)


class GammaDelay(DelayDensity):
    """Gamma(shape, scale) delay: the thesis's keepaway model (2.0, 0.28 s: mean 0.56 s, mode 0.28 s).

    CDF(x) = P(shape, x / scale), the regularised lower incomplete gamma (``torch.special.gammainc``).
    """

    def __init__(self, shape: float = 2.0, scale: float = 0.28) -> None:
        if not (math.isfinite(shape) and shape > 0):
            raise ValueError(f"GammaDelay shape must be a finite number > 0, got {shape!r}")
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"GammaDelay scale must be a finite number of seconds > 0, got {scale!r}")
        self.shape = float(shape)
        self.scale = float(scale)

    def cdf(self, x: Tensor) -> Tensor:
        x = torch.as_tensor(x, dtype=torch.float64).clamp_min(0.0)
        return torch.special.gammainc(torch.tensor(self.shape, dtype=torch.float64), x / self.scale)

    def __repr__(self) -> str:
        return f"GammaDelay(shape={self.shape}, scale={self.scale})"


class UniformDelay(DelayDensity):
    """Uniform delay on ``[a, b]`` seconds: Knox's later code uses [0.2, 0.8], Deep TAMER [0.2, 4]."""

    def __init__(self, a: float = 0.2, b: float = 0.8) -> None:
        if not (math.isfinite(a) and math.isfinite(b) and 0 <= a < b):
            raise ValueError(f"UniformDelay needs finite 0 <= a < b seconds, got a={a!r}, b={b!r}")
        self.a = float(a)
        self.b = float(b)

    def cdf(self, x: Tensor) -> Tensor:
        x = torch.as_tensor(x, dtype=torch.float64)
        return ((x - self.a) / (self.b - self.a)).clamp(0.0, 1.0)

    def __repr__(self) -> str:
        return f"UniformDelay(a={self.a}, b={self.b})"


class PreviousStep:
    """All credit to the step just completed: the latest step that started strictly before the feedback.

    The Tetris default (thesis Algorithms 1-3): a step is one whole piece placement, and feedback given while
    the next piece falls judges the placement just made. It counts steps, not seconds, so ``credit_weights``'s
    delay ``window`` does not apply; ``max_age`` (seconds, None = no limit) optionally drops feedback that
    comes more than ``max_age`` after that step started.
    """

    def __init__(self, max_age: float | None = None) -> None:
        if max_age is not None and not (math.isfinite(max_age) and max_age > 0):
            raise ValueError(
                f"PreviousStep max_age must be None or a finite number of seconds > 0, got {max_age!r}"
            )
        self.max_age = None if max_age is None else float(max_age)

    def __repr__(self) -> str:
        return f"PreviousStep(max_age={self.max_age})"


CreditModel = DelayDensity | PreviousStep


def _as_times(x: Tensor | float | list[float], name: str) -> Tensor:
    t = torch.as_tensor(x, dtype=torch.float64)
    if t.is_complex():
        raise ValueError(f"{name} must be real times in seconds")
    return t


def credit_weights(
    event_time: Tensor | float,
    step_starts: Tensor | list[float],
    step_ends: Tensor | list[float],
    delay: CreditModel,
    window: float | None = 0.5,
    renormalise: bool = False,
) -> Tensor:
    """Credit of each step for feedback given at ``event_time`` (thesis Figure 5.5; Knox & Stone 2009).

    ``c_i = integral of f over [t - t_{i+1}, t - t_i]``, with both limits clipped to the delay window
    ``[0, window]``: steps that started after the event get 0 (they cannot be its cause), steps that ended
    more than ``window`` before it get 0, and a step partly inside the window gets only that part's mass.
    Only times matter, not episode boundaries: feedback that comes after an episode's last step still
    credits that episode's last steps. An event before every step gives all zeros.

    :param event_time: feedback time(s) in seconds, any shape ``E`` (a scalar for one event).
    :param step_starts: ``[..., N]`` start ``t_i`` of each step, chronological and non-overlapping.
    :param step_ends: ``[..., N]`` end ``t_{i+1}`` of each step (``inf`` for a step still running).
    :param delay: a ``DelayDensity`` (``GammaDelay``, ``UniformDelay``) or ``PreviousStep``.
    :param window: the longest delay credited, seconds; ``None`` for no limit. Ignored by ``PreviousStep``.
    :param renormalise: scale each event's credits to sum to 1 when their sum is > 0 (the raw gamma(2, 0.28)
        credits over 500 ms sum to 0.533).
    :return: float64 credits of shape ``broadcast(E + (1,), step_starts.shape)``: ``E + (N,)`` for 1-D steps;
        with ``[B, N]`` steps and ``[B]`` events, one row of steps per event.
    """
    t = _as_times(event_time, "event_time").unsqueeze(-1)
    starts = _as_times(step_starts, "step_starts")
    ends = _as_times(step_ends, "step_ends")
    if starts.ndim == 0 or starts.shape != ends.shape:
        raise ValueError(
            f"step_starts and step_ends must have the same shape [..., N], got {tuple(starts.shape)} "
            f"and {tuple(ends.shape)}"
        )
    if not torch.isfinite(t).all():
        raise ValueError("event_time must be finite seconds")
    if not torch.isfinite(starts).all() or torch.isnan(ends).any():
        raise ValueError("step_starts must be finite and step_ends finite or inf (a step still running)")
    if (ends < starts).any():
        raise ValueError("every step must end at or after it starts (step_ends >= step_starts)")
    if (ends[..., :-1] > starts[..., 1:]).any():
        raise ValueError(
            "steps must be chronological and non-overlapping (step_ends[i] <= step_starts[i + 1])"
        )
    if window is not None and not (math.isfinite(window) and window > 0):
        raise ValueError(f"window must be None or a finite number of seconds > 0, got {window!r}")

    if isinstance(delay, PreviousStep):
        began = starts < t
        n = starts.shape[-1]
        index = torch.arange(n).expand(torch.broadcast_shapes(t.shape, starts.shape))
        last = torch.where(began, index, -1).amax(dim=-1, keepdim=True)
        credits = (index == last).to(torch.float64)
        if delay.max_age is not None:
            credits = credits * (t - starts <= delay.max_age)
        return credits
    if not isinstance(delay, DelayDensity):
        raise TypeError(f"delay must be a DelayDensity or PreviousStep, got {type(delay).__name__}")

    limit = math.inf if window is None else window
    lo = (t - ends).clamp(0.0, limit)
    hi = (t - starts).clamp(0.0, limit)
    credits = delay.mass(lo, hi)
    if renormalise:
        total = credits.sum(dim=-1, keepdim=True)
        credits = torch.where(total > 0, credits / torch.where(total > 0, total, 1.0), credits)
    return credits
