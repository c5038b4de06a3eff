"""What counts as a frame (an image observation) wherever a layer has to tell frames from vectors: the
task's spaces (``envs``), the CNN that reads them (``models``) and the saved policies (``agents``)."""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["image_shape"]


def image_shape(shape: Sequence[int]) -> tuple[int, int, int] | None:
    """``(height, width, channels)`` where ``shape`` is one frame (channels last, 1, 3 or 4 of them, each
    side at least 8), else None."""
    if len(shape) != 3 or int(shape[2]) not in (1, 3, 4) or min(int(shape[0]), int(shape[1])) < 8:
        return None
    return int(shape[0]), int(shape[1]), int(shape[2])
