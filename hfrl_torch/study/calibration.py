"""The reaction-time calibration: a person's measured delays set their credit window.

The reaction allowance (``trainer.reaction_s``) is the median delay clamped to [0.15, 1.0] s; the gamma
delay density (``human.gamma_shape``/``gamma_scale``, where the condition credits by gamma) is the
method-of-moments fit (shape = mean^2 / var, scale = var / mean) of the same delays.
"""

from __future__ import annotations

import math
import statistics
from typing import Any

MIN_DELAY_S = 0.05
MAX_DELAY_S = 3.0
MAX_TRIALS = 50
REACTION_RANGE_S = (0.15, 1.0)
MIN_FIT = 3  # delays needed for a gamma fit


def check_delays(delays: Any) -> list[float]:
    """The delays as floats; ValueError with one line unless a list of 1..50 numbers in 0.05..3.0 s."""
    if not isinstance(delays, list) or not 1 <= len(delays) <= MAX_TRIALS:
        raise ValueError(f"delays_s must be a list of 1..{MAX_TRIALS} numbers")
    out = []
    for i, d in enumerate(delays):
        ok = isinstance(d, (int, float)) and not isinstance(d, bool) and math.isfinite(d)
        if not ok or not MIN_DELAY_S <= d <= MAX_DELAY_S:
            raise ValueError(
                f"delays_s[{i}]={d!r} is invalid: must be a number in {MIN_DELAY_S}..{MAX_DELAY_S}"
            )
        out.append(float(d))
    return out


def fit(delays: Any) -> dict[str, Any]:
    """``{"delays_s", "reaction_s", "gamma_shape", "gamma_scale"}`` of the measured delays; the gamma
    parameters are None with fewer than 3 delays or no spread (the run keeps its configured density)."""
    values = check_delays(delays)
    low, high = REACTION_RANGE_S
    reaction = min(max(statistics.median(values), low), high)
    shape = scale = None
    if len(values) >= MIN_FIT:
        mean, var = statistics.fmean(values), statistics.pvariance(values)
        if var > 1e-9:
            shape, scale = mean * mean / var, var / mean
    return {
        "delays_s": values,
        "reaction_s": round(reaction, 4),
        "gamma_shape": None if shape is None else round(shape, 4),
        "gamma_scale": None if scale is None else round(scale, 5),
    }
