"""The calibration fit: the median clamped to [0.15, 1.0] s and a method-of-moments gamma; bounded input."""

from __future__ import annotations

import random
import statistics

import pytest

from hfrl_torch.study.calibration import check_delays, fit


def test_median_and_clamp() -> None:
    assert fit([0.3, 0.5, 0.4])["reaction_s"] == 0.4
    assert fit([0.05, 0.06, 0.1])["reaction_s"] == 0.15
    assert fit([2.5, 3.0, 1.5])["reaction_s"] == 1.0


def test_gamma_moments_recover_the_density() -> None:
    rng = random.Random(3)
    delays = [min(max(rng.gammavariate(2.0, 0.28), 0.05), 3.0) for _ in range(50)]
    out = fit(delays)
    mean, var = statistics.fmean(delays), statistics.pvariance(delays)
    assert out["gamma_shape"] == pytest.approx(mean**2 / var, rel=1e-3)
    assert out["gamma_scale"] == pytest.approx(var / mean, rel=1e-3)
    assert out["gamma_shape"] * out["gamma_scale"] == pytest.approx(mean, rel=1e-3)
    assert 1.0 < out["gamma_shape"] < 4.0 and 0.1 < out["gamma_scale"] < 0.6  # near gamma(2, 0.28)
    assert out["delays_s"] == delays


def test_no_fit_without_spread_or_trials() -> None:
    assert fit([0.4, 0.4, 0.4])["gamma_shape"] is None
    out = fit([0.3, 0.6])
    assert out["gamma_shape"] is None and out["gamma_scale"] is None and out["reaction_s"] == 0.45


@pytest.mark.parametrize(
    ("delays", "message"),
    [
        ([], "delays_s must be a list of 1..50 numbers"),
        ([0.3] * 51, "delays_s must be a list of 1..50 numbers"),
        ("0.3", "delays_s must be a list"),
        ([0.3, 0.01], r"delays_s\[1\]=0.01 is invalid: must be a number in 0.05..3.0"),
        ([3.5], r"delays_s\[0\]=3.5 is invalid"),
        ([float("nan")], r"delays_s\[0\]=nan is invalid"),
        ([True], r"delays_s\[0\]=True is invalid"),
        (["0.3"], r"delays_s\[0\]='0.3' is invalid"),
    ],
)
def test_bad_delays(delays: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        check_delays(delays)
