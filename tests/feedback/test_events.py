"""Feedback events (validation) and the thread-safe queue between a trainer thread and the training loop."""

from __future__ import annotations

import dataclasses
import math
import threading
import time

import numpy as np
import pytest

from hfrl_torch.feedback.events import (
    FeedbackEvent,
    FeedbackQueue,
    FeedbackQueueClosedError,
    FeedbackQueueFullError,
)


def _ev(i: int, source: str = "simulated:oracle") -> FeedbackEvent:
    return FeedbackEvent(time=1000.0 + i, value=1.0 if i % 2 else -1.0, source=source, step=i, episode=0)


# ---------------------------------------------------------------- events


def test_event_fields_defaults_and_coercion():
    ev = FeedbackEvent(
        time=np.float64(12.5), value=1, source="human:browser", session="s1", step=3, episode=2
    )
    assert (ev.time, ev.value, ev.step, ev.episode) == (12.5, 1.0, 3, 2)
    assert type(ev.time) is float and type(ev.value) is float
    bare = FeedbackEvent(time=1.0, value=-1.0, source="replay")
    assert (bare.session, bare.step, bare.episode, bare.seq) == ("", -1, -1, -1)
    assert list(ev.to_dict()) == ["time", "step", "episode", "value", "source", "session", "seq"]
    with pytest.raises(dataclasses.FrozenInstanceError):
        ev.value = 2.0  # type: ignore[misc]


@pytest.mark.parametrize(
    ("field", "bad"),
    [
        ("time", math.nan),
        ("time", math.inf),
        ("time", "now"),
        ("value", math.nan),
        ("value", -math.inf),
        ("value", 1000.5),
        ("value", -2e3),
        ("value", True),
        ("source", ""),
        ("source", "  "),
        ("source", None),
        ("session", 3),
        ("step", -2),
        ("step", 1.5),
        ("episode", -5),
    ],
)
def test_bad_event_names_the_field(field, bad):
    kwargs = {"time": 1.0, "value": 1.0, "source": "replay", "session": "s", "step": 0, "episode": 0}
    kwargs[field] = bad
    with pytest.raises(ValueError, match=rf"FeedbackEvent\.{field} must") as info:
        FeedbackEvent(**kwargs)
    assert "\n" not in str(info.value)


def test_value_limits_are_inclusive():
    assert FeedbackEvent(time=0.0, value=1e3, source="x").value == 1e3
    assert FeedbackEvent(time=0.0, value=-1e3, source="x").value == -1e3


# ---------------------------------------------------------------- queue


def test_queue_fifo_and_nonblocking_drain():
    q = FeedbackQueue()
    assert q.drain() == []
    for i in range(5):
        q.put(_ev(i))
    assert len(q) == 5
    assert [e.step for e in q.drain()] == [0, 1, 2, 3, 4]
    assert q.drain() == [] and len(q) == 0


def test_drop_oldest_when_full():
    q = FeedbackQueue(maxsize=3)
    for i in range(5):
        q.put(_ev(i))
    assert q.dropped == 2
    assert [e.step for e in q.drain()] == [2, 3, 4]


def test_error_when_full():
    q = FeedbackQueue(maxsize=2, overflow="error")
    q.put(_ev(0))
    q.put(_ev(1))
    with pytest.raises(FeedbackQueueFullError, match="full"):
        q.put(_ev(2))
    assert [e.step for e in q.drain()] == [0, 1]
    assert q.dropped == 0


def test_close_refuses_puts_but_keeps_what_is_left():
    q = FeedbackQueue()
    q.put(_ev(0))
    q.close()
    q.close()
    assert q.closed
    with pytest.raises(FeedbackQueueClosedError):
        q.put(_ev(1))
    assert [e.step for e in q.drain()] == [0]


def test_bad_queue_arguments():
    with pytest.raises(ValueError, match="maxsize"):
        FeedbackQueue(maxsize=0)
    with pytest.raises(ValueError, match="overflow"):
        FeedbackQueue(overflow="block")  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="FeedbackEvent"):
        FeedbackQueue().put({"time": 1.0})  # type: ignore[arg-type]


def test_drain_timeout_waits_for_an_event_or_gives_up():
    q = FeedbackQueue()
    t0 = time.monotonic()
    assert q.drain(timeout=0.05) == []
    assert time.monotonic() - t0 >= 0.04
    timer = threading.Timer(0.05, q.put, args=(_ev(7),))
    timer.start()
    got = q.drain(timeout=10.0)
    timer.join()
    assert [e.step for e in got] == [7]


def test_producer_threads_lose_nothing_and_keep_their_order():
    q = FeedbackQueue(maxsize=100_000)
    n_producers, per = 4, 500

    def produce(k: int) -> None:
        for i in range(per):
            q.put(_ev(i, source=f"simulated:{k}"))

    threads = [threading.Thread(target=produce, args=(k,)) for k in range(n_producers)]
    for th in threads:
        th.start()
    got: list[FeedbackEvent] = []
    deadline = time.monotonic() + 30.0
    while len(got) < n_producers * per and time.monotonic() < deadline:
        got.extend(q.drain(timeout=0.01))
    for th in threads:
        th.join()
    got.extend(q.drain())
    assert len(got) == n_producers * per
    assert q.dropped == 0
    for k in range(n_producers):
        assert [e.step for e in got if e.source == f"simulated:{k}"] == list(range(per))


def test_close_wakes_a_waiting_drain():
    q = FeedbackQueue()
    threading.Timer(0.05, q.close).start()
    t0 = time.monotonic()
    assert q.drain(timeout=10.0) == []
    assert time.monotonic() - t0 < 5.0
