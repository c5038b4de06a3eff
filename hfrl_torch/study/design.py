"""The study's between-subjects design: seeded permuted blocks, counterbalanced and blinded.

Enrolment ``i`` falls in block ``i // k`` (``k`` conditions); each block holds every condition once, in an
order drawn from the study seed and the block's number, so any prefix of enrolments is balanced to within
one participant per condition and the order cannot be guessed without the seed. The label is never shown
to a participant.
"""

from __future__ import annotations

import random
from collections.abc import Sequence

DESIGNS = ("blocked",)


def block_order(labels: Sequence[str], seed: int, block: int) -> list[str]:
    """The conditions of block ``block``, in the order the seed draws for it."""
    order = list(labels)
    random.Random(f"hfrl_torch.study:{seed}:{block}").shuffle(order)
    return order


def condition_for(index: int, labels: Sequence[str], seed: int) -> str:
    """The condition of enrolment ``index`` (0-based)."""
    if index < 0:
        raise ValueError(f"index={index} is invalid: must be >= 0")
    if not labels:
        raise ValueError("labels is empty: a design needs at least one condition")
    return block_order(labels, seed, index // len(labels))[index % len(labels)]
