"""Credit assignment for delayed feedback: the spec's gamma numbers, uniform cases worked by hand, the
previous-step scheme, windows, episode ends, batching, and properties of any credit vector."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.feedback.credit import GammaDelay, PreviousStep, UniformDelay, credit_weights

T0 = 1_700_000_000.0  # a wall-clock time: float32 could not tell 100 ms steps apart here
ATOL = 1e-6  # float64 resolves times near T0 to 2.4e-7 s, so credits computed from them agree to about that


def _steps(n: int, dt: float = 0.1, t0: float = T0) -> tuple[torch.Tensor, torch.Tensor]:
    edges = t0 + dt * torch.arange(n + 1, dtype=torch.float64)
    return edges[:-1], edges[1:]


def _gamma2_cdf(x: float, scale: float = 0.28) -> float:
    """Closed form of the gamma(2, scale) CDF: 1 - exp(-x/s) (1 + x/s)."""
    return 1.0 - math.exp(-x / scale) * (1.0 + x / scale)


# ---------------------------------------------------------------- gamma: the spec's numbers


def test_gamma_spec_numbers_newest_first():
    starts, ends = _steps(10)
    c = credit_weights(T0 + 1.0, starts, ends, GammaDelay(2.0, 0.28), window=0.5)
    newest_first = c.flip(0)
    assert torch.allclose(
        newest_first[:5], torch.tensor([0.050, 0.110, 0.130, 0.127, 0.115], dtype=c.dtype), atol=5e-4
    )
    assert torch.all(newest_first[5:] == 0)
    assert round(float(c.sum()), 3) == 0.533
    assert c.dtype == torch.float64


def test_gamma_renormalised_sums_to_one_and_keeps_proportions():
    starts, ends = _steps(10)
    raw = credit_weights(T0 + 1.0, starts, ends, GammaDelay(), window=0.5)
    norm = credit_weights(T0 + 1.0, starts, ends, GammaDelay(), window=0.5, renormalise=True)
    assert float(norm.sum()) == pytest.approx(1.0, abs=ATOL)
    assert torch.allclose(norm, raw / raw.sum())


def test_gamma_cdf_matches_closed_form():
    d = GammaDelay(2.0, 0.28)
    xs = [0.0, 0.05, 0.28, 0.5, 1.3]
    got = d.cdf(torch.tensor(xs, dtype=torch.float64))
    assert torch.allclose(got, torch.tensor([_gamma2_cdf(x) for x in xs], dtype=torch.float64), atol=1e-12)
    assert float(d.cdf(torch.tensor(-1.0))) == 0.0


def test_step_partly_inside_window_gets_only_that_part():
    # one step [t - 0.6, t - 0.4): delays [0.4, 0.6], window cuts at 0.5
    t = T0 + 10.0
    c = credit_weights(t, [t - 0.6], [t - 0.4], GammaDelay(), window=0.5)
    assert float(c[0]) == pytest.approx(_gamma2_cdf(0.5) - _gamma2_cdf(0.4), abs=ATOL)
    c_free = credit_weights(t, [t - 0.6], [t - 0.4], GammaDelay(), window=None)
    assert float(c_free[0]) == pytest.approx(_gamma2_cdf(0.6) - _gamma2_cdf(0.4), abs=ATOL)


def test_steps_older_than_window_get_zero():
    t = T0 + 5.0
    c = credit_weights(t, [t - 2.0, t - 0.7], [t - 1.0, t - 0.5], GammaDelay(), window=0.5)
    assert torch.equal(c, torch.zeros(2, dtype=torch.float64))


def test_feedback_after_episode_end_credits_its_last_steps():
    # the episode's 5 steps end at T0 + 0.5; the person presses 0.2 s later
    starts, ends = _steps(5)
    c = credit_weights(T0 + 0.7, starts, ends, GammaDelay(), window=0.5)
    expected = [0.0, 0.0, _gamma2_cdf(0.5) - _gamma2_cdf(0.4)]
    expected += [_gamma2_cdf(0.4) - _gamma2_cdf(0.3), _gamma2_cdf(0.3) - _gamma2_cdf(0.2)]
    assert torch.allclose(c, torch.tensor(expected, dtype=torch.float64), atol=ATOL)
    assert float(c[-1]) > 0


def test_step_in_progress_and_steps_after_event():
    # step 2 is still running (end = inf); step 3 starts after the event: no credit
    t = T0 + 0.25
    starts = torch.tensor([T0, T0 + 0.1, T0 + 0.2], dtype=torch.float64)
    ends = torch.tensor([T0 + 0.1, T0 + 0.2, math.inf], dtype=torch.float64)
    c = credit_weights(t, starts, ends, GammaDelay(), window=0.5)
    assert float(c[2]) == pytest.approx(_gamma2_cdf(0.05), abs=ATOL)
    assert float(c[1]) == pytest.approx(_gamma2_cdf(0.15) - _gamma2_cdf(0.05), abs=ATOL)
    later = credit_weights(t, [T0 + 0.3], [T0 + 0.4], GammaDelay(), window=0.5)
    assert float(later[0]) == 0.0


@pytest.mark.parametrize("delay", [GammaDelay(), UniformDelay(0.0, 0.8), PreviousStep()])
def test_event_before_any_step_gives_zeros(delay):
    starts, ends = _steps(4)
    c = credit_weights(T0 - 0.3, starts, ends, delay, window=0.5)
    assert torch.equal(c, torch.zeros(4, dtype=torch.float64))
    at_start = credit_weights(T0, starts, ends, delay, window=0.5)
    assert torch.equal(at_start, torch.zeros(4, dtype=torch.float64))


# ---------------------------------------------------------------- uniform [0.2, 0.8], worked by hand


def test_uniform_100ms_steps_500ms_window():
    # delays [0, .1] and [.1, .2] are below 0.2: 0; [.2,.3], [.3,.4], [.4,.5] each hold 0.1 / 0.6
    starts, ends = _steps(8)
    c = credit_weights(T0 + 0.8, starts, ends, UniformDelay(0.2, 0.8), window=0.5).flip(0)
    sixth = 1.0 / 6.0
    assert torch.allclose(
        c, torch.tensor([0, 0, sixth, sixth, sixth, 0, 0, 0], dtype=torch.float64), atol=ATOL
    )
    norm = credit_weights(T0 + 0.8, starts, ends, UniformDelay(0.2, 0.8), window=0.5, renormalise=True).flip(
        0
    )
    third = 1.0 / 3.0
    assert torch.allclose(
        norm, torch.tensor([0, 0, third, third, third, 0, 0, 0], dtype=torch.float64), atol=ATOL
    )


def test_uniform_without_window_covers_all_mass():
    starts, ends = _steps(10)
    c = credit_weights(T0 + 1.0, starts, ends, UniformDelay(0.2, 0.8), window=None).flip(0)
    expected = torch.tensor([0, 0] + [1 / 6] * 6 + [0, 0], dtype=torch.float64)
    assert torch.allclose(c, expected, atol=ATOL)
    assert float(c.sum()) == pytest.approx(1.0, abs=ATOL)


def test_uniform_uneven_steps_by_hand():
    # steps [0, .25), [.25, .35), [.35, 1.0) (still running at t = .9); event at t = .9
    starts = torch.tensor([0.0, 0.25, 0.35], dtype=torch.float64) + T0
    ends = torch.tensor([0.25, 0.35, 1.0], dtype=torch.float64) + T0
    d = UniformDelay(0.2, 0.8)
    # window .5: step 2 has delays [0, .55] -> [0, .5]: (.5 - .2) / .6 = .5; the others lie past the window
    c = credit_weights(T0 + 0.9, starts, ends, d, window=0.5)
    assert torch.allclose(c, torch.tensor([0.0, 0.0, 0.5], dtype=torch.float64), atol=ATOL)
    # no window: step 0 delays [.65, .9] -> .15/.6; step 1 [.55, .65] -> .1/.6; step 2 [0, .55] -> .35/.6
    c = credit_weights(T0 + 0.9, starts, ends, d, window=None)
    assert torch.allclose(c, torch.tensor([0.25, 1 / 6, 0.35 / 0.6], dtype=torch.float64), atol=ATOL)


# ---------------------------------------------------------------- previous step (Tetris)


def test_previous_step_one_hot_on_latest_started_step():
    starts, ends = _steps(5, dt=0.2)
    c = credit_weights(T0 + 0.5, starts, ends, PreviousStep())
    assert torch.equal(c, torch.tensor([0, 0, 1, 0, 0], dtype=torch.float64))
    # exactly at a step boundary the step just started has not been seen yet
    c = credit_weights(T0 + 0.4, starts, ends, PreviousStep())
    assert torch.equal(c, torch.tensor([0, 1, 0, 0, 0], dtype=torch.float64))


def test_previous_step_ignores_window_and_credits_after_episode_end():
    starts, ends = _steps(5, dt=0.2)
    c = credit_weights(T0 + 5.0, starts, ends, PreviousStep(), window=0.5, renormalise=True)
    assert torch.equal(c, torch.tensor([0, 0, 0, 0, 1], dtype=torch.float64))
    aged = credit_weights(T0 + 5.0, starts, ends, PreviousStep(max_age=1.0))
    assert torch.equal(aged, torch.zeros(5, dtype=torch.float64))
    fresh = credit_weights(T0 + 1.5, starts, ends, PreviousStep(max_age=1.0))
    assert torch.equal(fresh, torch.tensor([0, 0, 0, 0, 1], dtype=torch.float64))


# ---------------------------------------------------------------- batching


@pytest.mark.parametrize("delay", [GammaDelay(), UniformDelay(0.2, 0.8), PreviousStep()])
def test_batch_of_events_equals_one_at_a_time(delay):
    starts, ends = _steps(12)
    times = T0 + torch.tensor([-0.1, 0.05, 0.33, 0.9, 1.2, 2.5], dtype=torch.float64)
    batch = credit_weights(times, starts, ends, delay, window=0.5, renormalise=True)
    assert batch.shape == (6, 12)
    for k in range(6):
        one = credit_weights(float(times[k]), starts, ends, delay, window=0.5, renormalise=True)
        assert torch.allclose(batch[k], one)


def test_batched_steps_one_row_per_event():
    s1, e1 = _steps(6)
    s2, e2 = _steps(6, dt=0.15)
    times = torch.tensor([T0 + 0.6, T0 + 0.5], dtype=torch.float64)
    c = credit_weights(times, torch.stack([s1, s2]), torch.stack([e1, e2]), GammaDelay())
    assert c.shape == (2, 6)
    assert torch.allclose(c[0], credit_weights(T0 + 0.6, s1, e1, GammaDelay()))
    assert torch.allclose(c[1], credit_weights(T0 + 0.5, s2, e2, GammaDelay()))


# ---------------------------------------------------------------- validation


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"step_starts": [0.0, 1.0], "step_ends": [1.0]}, "same shape"),
        ({"step_starts": [0.0, 0.5], "step_ends": [1.0, 1.5]}, "non-overlapping"),
        ({"step_starts": [1.0], "step_ends": [0.5]}, "end at or after"),
        ({"event_time": math.nan}, "event_time"),
        ({"window": 0.0}, "window"),
        ({"step_starts": [math.nan], "step_ends": [1.0]}, "step_starts"),
    ],
)
def test_bad_inputs_raise_one_line(kwargs, match):
    args = {"event_time": 2.0, "step_starts": [0.0], "step_ends": [1.0], "delay": GammaDelay(), **kwargs}
    with pytest.raises(ValueError, match=match):
        credit_weights(**args)


def test_bad_density_parameters():
    with pytest.raises(ValueError, match="shape"):
        GammaDelay(shape=0.0)
    with pytest.raises(ValueError, match="scale"):
        GammaDelay(scale=-1.0)
    with pytest.raises(ValueError, match="a < b"):
        UniformDelay(0.8, 0.2)
    with pytest.raises(ValueError, match="max_age"):
        PreviousStep(max_age=0.0)
    with pytest.raises(TypeError, match="DelayDensity"):
        credit_weights(1.0, [0.0], [0.5], delay="gamma")  # type: ignore[arg-type]


# ---------------------------------------------------------------- properties

_delays = st.one_of(
    st.builds(GammaDelay, st.floats(0.5, 5.0), st.floats(0.05, 1.0)),
    st.tuples(st.floats(0.0, 1.0), st.floats(0.05, 2.0)).map(lambda ab: UniformDelay(ab[0], ab[0] + ab[1])),
)


@settings(max_examples=60, deadline=None, derandomize=True)
@given(
    durations=st.lists(st.floats(0.01, 0.5), min_size=1, max_size=20),
    offset=st.floats(-1.0, 6.0),
    delay=_delays,
    window=st.one_of(st.none(), st.floats(0.05, 3.0)),
)
def test_credits_nonnegative_bounded_and_renormalise_to_one(durations, offset, delay, window):
    d = torch.tensor(durations, dtype=torch.float64)
    edges = T0 + torch.cat([torch.zeros(1, dtype=torch.float64), d.cumsum(0)])
    starts, ends = edges[:-1], edges[1:]
    t = T0 + offset
    raw = credit_weights(t, starts, ends, delay, window=window)
    assert (raw >= 0).all()
    assert float(raw.sum()) <= 1.0 + 1e-9
    limit = math.inf if window is None else window

    def clip(x: float) -> torch.Tensor:
        return torch.tensor(min(max(x, 0.0), limit), dtype=torch.float64)

    # contiguous steps: the credits add up to the delay mass between the first start and the last end
    expected = float(delay.cdf(clip(t - float(starts[0]))) - delay.cdf(clip(t - float(ends[-1]))))
    assert float(raw.sum()) == pytest.approx(expected, abs=ATOL)
    norm = credit_weights(t, starts, ends, delay, window=window, renormalise=True)
    if float(raw.sum()) > 0:
        assert float(norm.sum()) == pytest.approx(1.0, abs=ATOL)
    else:
        assert torch.equal(norm, raw)


@settings(max_examples=40, deadline=None, derandomize=True)
@given(durations=st.lists(st.floats(0.01, 0.5), min_size=1, max_size=20), offset=st.floats(-1.0, 6.0))
def test_previous_step_is_one_hot_or_zero(durations, offset):
    d = torch.tensor(durations, dtype=torch.float64)
    edges = T0 + torch.cat([torch.zeros(1, dtype=torch.float64), d.cumsum(0)])
    starts, ends = edges[:-1], edges[1:]
    c = credit_weights(T0 + offset, starts, ends, PreviousStep())
    started = int((starts < T0 + offset).sum())
    if started == 0:
        assert float(c.sum()) == 0.0
    else:
        assert float(c.sum()) == 1.0
        assert int(c.argmax()) == started - 1
