"""Draw a Tetris board as an RGB image (for TensorBoard, GIFs and the Gymnasium render)."""

from __future__ import annotations

import numpy as np


def render_board(cells: np.ndarray, scale: int = 16) -> np.ndarray:
    """[H, W] bool cells (row 0 at the bottom) to an [H*scale, W*scale, 3] uint8 image, top row first."""
    h, w = cells.shape
    img = np.full((h, w, 3), 24, np.uint8)
    img[cells[::-1].astype(bool)] = (90, 170, 230)
    img = img.repeat(scale, 0).repeat(scale, 1)
    img[::scale, :, :] = 48
    img[:, ::scale, :] = 48
    return img
