"""The feedback channel: events wait on each board's clock, then enter the tensordict, oldest first."""

from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.feedback.events import SOURCE_KINDS, FeedbackEvent


def _ev(time: float, value: float, source: str = "simulated:oracle") -> FeedbackEvent:
    return FeedbackEvent(time=time, value=value, source=source)


def test_events_wait_for_their_time_on_their_boards_clock():
    ch = FeedbackChannel(2)
    ch.put(torch.tensor([1.0, -1.0]), torch.tensor([0.5, 2.0]), "simulated:oracle")
    out = ch.deliver(torch.tensor([1.0, 1.0]))
    assert out.batch_size == (2,) and out[keys.FEEDBACK].shape == (2, 4)
    assert out[keys.FEEDBACK_MASK].tolist() == [[True, False, False, False], [False] * 4]
    assert out[keys.FEEDBACK][0, 0] == 1.0 and out[keys.FEEDBACK_TIME][0, 0] == 0.5
    assert math.isnan(float(out[keys.FEEDBACK_TIME][1, 0])) and out[keys.FEEDBACK][1].eq(0).all()
    assert out[keys.FEEDBACK_SOURCE][0, 0] == SOURCE_KINDS.index("simulated")
    assert ch.pending == 1  # board 1's event is still on its way
    late = ch.deliver(torch.tensor([1.0, 2.0]))
    assert late[keys.FEEDBACK].tolist()[1][0] == -1.0 and ch.pending == 0


def test_zero_values_are_no_events_and_the_slots_come_oldest_first():
    ch = FeedbackChannel(1, slots=2)
    ch.put_events([[_ev(3.0, 1.0), _ev(1.0, -1.0), _ev(2.0, 1.0, "human:browser")]])
    ch.put(torch.tensor([0.0]), torch.tensor([0.0]), "simulated:oracle")
    assert ch.pending == 3
    first = ch.deliver(10.0)
    assert first[keys.FEEDBACK_TIME].tolist() == [[1.0, 2.0]] and first[keys.FEEDBACK].tolist() == [
        [-1.0, 1.0]
    ]
    assert first[keys.FEEDBACK_SOURCE].tolist() == [
        [SOURCE_KINDS.index("simulated"), SOURCE_KINDS.index("human")]
    ]
    second = ch.deliver(10.0)  # more due than K slots: the rest come next time, in order
    assert second[keys.FEEDBACK_TIME][0, 0] == 3.0 and second[keys.FEEDBACK_MASK].tolist() == [[True, False]]
    assert not ch.deliver(math.inf)[keys.FEEDBACK_MASK].any()


def test_a_full_queue_grows_and_loses_nothing():
    ch = FeedbackChannel(1, slots=1, capacity=2)
    for t in range(5):
        ch.put(torch.tensor([1.0]), torch.tensor([100.0 + t]), "simulated:oracle")
    assert ch.pending == 5 and ch.capacity >= 5
    times = [float(ch.deliver(1e9)[keys.FEEDBACK_TIME][0, 0]) for _ in range(5)]
    assert times == [100.0, 101.0, 102.0, 103.0, 104.0] and ch.pending == 0


def test_state_round_trips_the_waiting_events():
    ch = FeedbackChannel(2)
    ch.put(torch.tensor([1.0, 1.0]), torch.tensor([5.0, 1.0]), "replay")
    fresh = FeedbackChannel(2)
    fresh.load_state_dict(ch.state_dict())
    a, b = ch.deliver(torch.tensor([6.0, 6.0])), fresh.deliver(torch.tensor([6.0, 6.0]))
    assert all(torch.equal(a[k].nan_to_num(), b[k].nan_to_num()) for k in a.keys())  # noqa: SIM118
    with pytest.raises(CheckpointError, match="3 boards"):
        FeedbackChannel(3).load_state_dict(ch.state_dict())
    with pytest.raises(CheckpointError, match="feedback channel"):
        FeedbackChannel(2).load_state_dict({"time": 1})


def test_bad_shapes_and_sizes_are_refused():
    with pytest.raises(ValueError, match="capacity >= slots"):
        FeedbackChannel(1, slots=4, capacity=2)
    with pytest.raises(ValueError, match="2 boards got 3"):
        FeedbackChannel(2).put(torch.ones(3), torch.zeros(3), "replay")
    with pytest.raises(ValueError, match="events for 1"):
        FeedbackChannel(2).put_events([[]])


@settings(max_examples=60, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 2), st.floats(0.0, 50.0), st.sampled_from([-1.0, 1.0])),
        min_size=1,
        max_size=40,
    ),
    st.lists(st.floats(0.0, 60.0), min_size=1, max_size=8),
)
def test_every_event_is_delivered_once_at_or_after_its_time(events, clocks):
    """Whatever the order of puts and deliveries: each event comes out exactly once, never before its time,
    and each board's events come out in time order."""
    ch = FeedbackChannel(3, slots=2, capacity=4)
    for board, t, v in events:
        values, times = torch.zeros(3, dtype=torch.float64), torch.zeros(3, dtype=torch.float64)
        values[board], times[board] = v, t
        ch.put(values, times, "simulated:oracle")
    seen: list[list[float]] = [[], [], []]
    for now in [*sorted(clocks), 1e9, 1e9, 1e9, 1e9] + [1e9] * len(events):
        out = ch.deliver(now)
        for b in range(3):
            for k in range(2):
                if bool(out[keys.FEEDBACK_MASK][b, k]):
                    t = float(out[keys.FEEDBACK_TIME][b, k])
                    assert t <= now
                    seen[b].append(t)
    for b in range(3):
        assert sorted(seen[b]) == seen[b]
        assert sorted(seen[b]) == sorted(t for board, t, _ in events if board == b)
    assert ch.pending == 0


def test_collect_queues_a_polling_trainers_events_and_counts_them_per_board():
    class Polling:
        source = "human:browser"

        def __init__(self) -> None:
            self.left = [([1.0, 0.0], [0.2, 0.0]), ([-1.0, 1.0], [0.3, 0.4])]

        def poll(self, clock: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
            values, times = self.left.pop(0) if self.left else ([0.0, 0.0], [0.0, 0.0])
            return torch.tensor(values, dtype=torch.float64), torch.tensor(times, dtype=torch.float64)

    ch = FeedbackChannel(2)
    clock = torch.tensor([1.0, 1.0])
    assert ch.collect(Polling(), clock).tolist() == [2, 1] and ch.pending == 3
    assert ch.collect(object(), clock).tolist() == [0, 0] and ch.pending == 3  # a trainer without poll
    assert ch.deliver(clock)[keys.FEEDBACK_MASK].sum(-1).tolist() == [2, 1]


def test_put_board_queues_one_boards_events_and_refuses_a_board_it_lacks():
    ch = FeedbackChannel(3)
    ch.put_board(1, [FeedbackEvent(time=0.5, value=1.0, source="human:browser")])
    ch.put_board(2, [])
    out = ch.deliver(1.0)
    assert out[keys.FEEDBACK_MASK].any(-1).tolist() == [False, True, False]
    with pytest.raises(ValueError, match="board 3"):
        ch.put_board(3, [])
