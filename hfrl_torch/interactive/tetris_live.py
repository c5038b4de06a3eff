"""``train.py trainer=interactive`` on Tetris: what the page draws of the game a person watches."""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, placement_table

LATE_FEEDBACK_S = 0.8  # how long a live game waits after its last placement for feedback on it


def tetris_frame(td: TensorDictBase, episode: int, weight: float) -> dict[str, Any]:
    """What the page draws after a placement: the board, the cells just placed, lines, the action."""
    before = td[keys.BOARD][0]
    after = td["next", keys.BOARD][0]
    placed = (
        (after & ~before).nonzero().tolist()
        if int(td["next", keys.LINES].sum()) == int(td[keys.LINES].sum())
        else []
    )
    p, a = int(td[keys.PIECE][0]), int(td[keys.ACTION][0])
    table = placement_table(before.shape[1])
    column, orient = int(table.column[p, a]), int(table.orient[p, a])
    return {
        "type": "tetris",
        "board": after.to(torch.int64).tolist(),
        "placed": placed,
        "lines": int(td["next", keys.LINES].sum()),
        "pieces": int(td["next", keys.PIECES_PLACED].sum()),
        "episode": episode,
        "action": f"{PIECE_NAMES[p]} at column {column + 1}, rotation {orient}",
        "text": f"watching you (trust in your feedback: {weight:.2f})",
    }
