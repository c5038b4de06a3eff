"""Summary statistics with 95 % intervals, the way every result in this project is reported."""

from __future__ import annotations

import math

import torch


def summarize(values: torch.Tensor | list[float], floor: float | None = None) -> dict[str, float]:
    """Mean, s.d., median and a 95 % interval of the mean (normal approximation: mean +- 1.96 s.e.).

    With fewer than two values the interval collapses to the mean. ``floor`` clips the interval
    at a value the mean cannot go below (0 for lines or durations).
    """
    x = torch.as_tensor(values, dtype=torch.float64).flatten()
    n = x.numel()
    if n == 0:
        raise ValueError("summarize() needs at least one value")
    mean = float(x.mean())
    sd = float(x.std(unbiased=True)) if n > 1 else 0.0
    half = 1.96 * sd / math.sqrt(n) if n > 1 else 0.0
    return {
        "n": n,
        "mean": mean,
        "sd": sd,
        "median": float(x.median()) if n % 2 else float(x.sort().values[n // 2 - 1 : n // 2 + 1].mean()),
        "ci95_low": mean - half if floor is None else max(mean - half, floor),
        "ci95_high": mean + half,
        "min": float(x.min()),
        "max": float(x.max()),
    }
