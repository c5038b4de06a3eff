"""The keepaway records: the episode rows, clocks and counts the learning curves are read from."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.envs.keepaway.records import KeepawayRecords


def test_rows_clocks_and_ordinals_of_fields_sharing_learners() -> None:
    """Four fields, two per learner, three keepers: every entry of the rows worked out by hand."""
    rec = KeepawayRecords(4, 3, fields_per_learner=2)
    rec.advance(torch.tensor([5, 7, 2, 9]))
    rec.decided(torch.tensor([0, 1, 3]), torch.tensor([2, 0, 1]), torch.tensor([0, 1, 0]))
    rec.decided(torch.tensor([0, 3]), torch.tensor([1, 1]), torch.tensor([2, 0]))
    assert rec.learner_clock.tolist() == [12, 11]
    ended = torch.tensor([True, True, False, True])
    rec.finish(ended, torch.tensor([5, 7, 2, 9]))
    # field, ordinal, the learner's clock with this step's ended episodes in, duration, holds, decisions
    assert rec.table.tolist() == [
        [0, 0, 12, 5, 1, 0, 1, 1],
        [1, 1, 12, 7, 0, 1, 0, 0],
        [3, 0, 11, 9, 2, 0, 2, 0],
    ]
    assert rec.episodes.tolist() == [2, 1]
    assert rec.holds.tolist() == [0, 0, 0, 0] and int(rec.decisions.sum()) == 0
    rec.advance(torch.tensor([1, 0, 4, 3]))  # the new episodes' cycles count on from the finished ones
    assert rec.clock.tolist() == [6, 7, 4, 12]
    rec.finish(torch.tensor([False, False, True, False]), torch.tensor([1, 0, 4, 3]))
    assert rec.table[-1].tolist() == [2, 1, 16, 4, 0, 0, 0, 0]
    assert rec.episodes.tolist() == [2, 2]


def test_the_table_grows_past_its_buffer_and_survives_a_checkpoint() -> None:
    rec = KeepawayRecords(3, 2)
    for i in range(500):  # 1,500 rows: past the first buffer of 1,024
        rec.decided(torch.tensor([i % 3]), torch.tensor([i % 2]), torch.tensor([i % 3 == 0]).long())
        cycles = torch.tensor([i + 1, 2, 3])
        rec.advance(cycles)
        rec.finish(torch.ones(3, dtype=torch.bool), cycles)
    assert rec.table.shape == (1500, 7)
    assert rec.table[:, 1].tolist() == [e for e in range(500) for _ in range(3)]
    assert int(rec.table[:, 3].sum()) == sum(range(1, 501)) + 500 * 5
    again = KeepawayRecords(3, 2)
    again.load_state_dict(rec.state_dict())
    assert torch.equal(again.table, rec.table) and torch.equal(again.clock, rec.clock)
    again.advance(torch.tensor([1, 1, 1]))
    again.finish(torch.tensor([True, False, False]), torch.tensor([1, 1, 1]))
    assert again.table[-1, :4].tolist() == [0, 500, int(rec.clock[0]) + 1, 1]


def test_a_field_out_of_range_raises_instead_of_writing_past_the_records() -> None:
    rec = KeepawayRecords(2, 3)
    with pytest.raises(IndexError):
        rec.decided(torch.tensor([2]), torch.tensor([0]), torch.tensor([0]))
    with pytest.raises(IndexError):
        rec.decided(torch.tensor([0]), torch.tensor([3]), torch.tensor([0]))
    assert int(rec.decisions.sum()) == 0 and int(rec.holds.sum()) == 0
