"""The referee: turnover counter branches, ball out, end causes and reset boxes."""

from __future__ import annotations

import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.envs.keepaway.referee import (
    END_OUT,
    END_RUNNING,
    END_TAKEN,
    ball_in_region,
    end_cause,
    reset_positions,
    update_turnover_counter,
)

KD = 1.085
T = torch.tensor


def _count(
    counter: int, ball: tuple[float, float], keeper: tuple[float, float], taker: tuple[float, float]
) -> int:
    out = update_turnover_counter(T([counter]), T([ball]), T([[keeper]]), T([[taker]]), KD)
    return int(out.item())


def test_taker_near_increments_even_with_keeper_near() -> None:
    assert _count(2, (0.0, 0.0), (0.5, 0.0), (-0.5, 0.0)) == 3
    assert _count(0, (0.0, 0.0), (9.0, 0.0), (1.0, 0.0)) == 1


def test_keeper_alone_resets_counter() -> None:
    assert _count(3, (0.0, 0.0), (1.0, 0.0), (5.0, 0.0)) == 0


def test_nobody_near_leaves_counter_unchanged() -> None:
    assert _count(3, (0.0, 0.0), (2.0, 0.0), (0.0, 2.0)) == 3
    assert _count(0, (0.0, 0.0), (2.0, 0.0), (0.0, 2.0)) == 0


def test_ball_out_of_region_and_end_causes() -> None:
    inside = ball_in_region(T([[9.9, -9.9], [10.0, 0.0], [0.0, -10.5]]), 20.0, 20.0)
    assert inside.tolist() == [True, False, False]
    causes = end_cause(T([True, True, False, False]), T([2, 4, 0, 5]), 4)
    assert causes.tolist() == [END_RUNNING, END_TAKEN, END_OUT, END_OUT]


@settings(max_examples=80, deadline=None)
@given(
    counter=st.integers(0, 10),
    ball=st.tuples(st.floats(-3, 3), st.floats(-3, 3)),
    keepers=st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), min_size=1, max_size=3),
    takers=st.lists(st.tuples(st.floats(-3, 3), st.floats(-3, 3)), min_size=1, max_size=3),
)
def test_counter_never_decreases_except_to_zero(
    counter: int, ball: tuple[float, float], keepers: list, takers: list
) -> None:
    new = int(update_turnover_counter(T([counter]), T([ball]), T([keepers]), T([takers]), KD).item())
    assert new == 0 or new >= counter
    assert new <= counter + 1


def test_reset_positions_lie_in_their_boxes() -> None:
    gen = torch.Generator().manual_seed(3)
    for keepers in (3, 4, 5):
        kpos, tpos, ball = reset_positions(500, keepers, 3, 20.0, 20.0, gen, torch.device("cpu"))
        assert torch.allclose(ball, T([-6.0, -6.0]).expand(500, 2))
        assert (
            (tpos[..., 0] >= -10) & (tpos[..., 0] <= -7) & (tpos[..., 1] >= 7) & (tpos[..., 1] <= 10)
        ).all()
        x, y = kpos[..., 0], kpos[..., 1]
        corner0 = (x >= -10) & (x <= -7) & (y >= -10) & (y <= -7)
        corner1 = (x >= 7) & (x <= 10) & (y >= -10) & (y <= -7)
        corner2 = (x >= 7) & (x <= 10) & (y >= 7) & (y <= 10)
        centre = (x.abs() <= 1) & (y.abs() <= 1)
        assert (corner0 | corner1 | corner2 | centre).all()
        # every corner is taken by exactly one keeper, the rest are in the centre
        assert (corner0.sum(1) == 1).all() and (corner1.sum(1) == 1).all() and (corner2.sum(1) == 1).all()
        assert (centre.sum(1) == keepers - 3).all()
