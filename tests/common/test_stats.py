"""summarize(): the 95 % interval of the mean, its degenerate cases and its floor."""

from __future__ import annotations

import math

import pytest

from hfrl_torch.common.stats import summarize


def test_values_by_hand():
    s = summarize([1.0, 2.0, 3.0, 4.0])
    sd = math.sqrt(((1.5**2) * 2 + (0.5**2) * 2) / 3)
    assert s["mean"] == 2.5 and s["median"] == 2.5 and s["sd"] == pytest.approx(sd)
    assert s["ci95_low"] == pytest.approx(2.5 - 1.96 * sd / 2) and s["ci95_high"] == pytest.approx(
        2.5 + 1.96 * sd / 2
    )
    assert summarize([5.0, 1.0, 3.0])["median"] == 3.0


def test_single_value_and_floor():
    assert summarize([7.0])["ci95_low"] == summarize([7.0])["ci95_high"] == 7.0
    s = summarize([0.0, 0.0, 1.0], floor=0.0)
    assert s["ci95_low"] == 0.0 and s["ci95_high"] > s["mean"]
    assert summarize([0.0, 0.0, 1.0])["ci95_low"] < 0.0


def test_empty_is_an_error():
    with pytest.raises(ValueError, match="at least one value"):
        summarize([])
