"""TorchRL's partial-reset flag read with the public tensordict API, for transforms' ``_reset``."""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey


def reset_flags(tensordict: TensorDictBase, key: NestedKey, batch: torch.Size) -> torch.Tensor:
    """``[*batch]`` bool: the boards a reset restarts, read from the flag ``key`` of the tensordict the reset
    was called with (``[*batch]`` or ``[*batch, ...]``, any flag set restarts the board); every board when
    the flag is absent (a full reset)."""
    flags = tensordict.get(key, None)
    if flags is None:
        return torch.ones(batch, dtype=torch.bool, device=tensordict.device)
    return flags.reshape(*batch, -1).any(-1)
