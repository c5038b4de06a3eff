"""The permuted-block design: each block holds every condition once; seeded; different seeds differ."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hfrl_torch.study.design import block_order, condition_for

LABELS = ["tetris_adaptive", "tetris_human_only", "keepaway_adaptive", "keepaway_human_only"]


@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 6), blocks=st.integers(1, 8))
def test_every_block_holds_each_condition_once(seed: int, k: int, blocks: int) -> None:
    labels = [f"c{i}" for i in range(k)]
    assigned = [condition_for(i, labels, seed) for i in range(k * blocks)]
    for b in range(blocks):
        assert sorted(assigned[b * k : (b + 1) * k]) == labels
    for n in range(len(assigned) + 1):  # any prefix is balanced to within one per condition
        counts = [assigned[:n].count(c) for c in labels]
        assert max(counts) - min(counts) <= 1


def test_seeded_and_seeds_differ() -> None:
    first = [condition_for(i, LABELS, 7) for i in range(40)]
    assert first == [condition_for(i, LABELS, 7) for i in range(40)]
    others = {tuple(condition_for(i, LABELS, s) for i in range(40)) for s in range(20)}
    assert len(others) == 20  # 24^10 sequences: twenty seeds give twenty designs
    orders = {tuple(block_order(LABELS, 7, b)) for b in range(30)}
    assert len(orders) > 5  # blocks are not all in one order (counterbalanced)


def test_bad_index() -> None:
    with pytest.raises(ValueError, match="index=-1 is invalid"):
        condition_for(-1, LABELS, 0)
