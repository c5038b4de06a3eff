"""Tensors handed to compiled (numba) kernels: contiguous CPU numpy arrays that share the tensor's memory
where they can, so the kernels read and write the torch state in place."""

from __future__ import annotations

import numpy as np
import torch


def as_numpy(x: torch.Tensor, dtype: torch.dtype | None = None) -> np.ndarray:
    """A contiguous CPU numpy view of ``x`` in ``dtype`` (a copy where a move, conversion or compaction is
    needed)."""
    return x.detach().to("cpu", dtype or x.dtype).contiguous().numpy()
