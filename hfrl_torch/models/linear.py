"""Linear value of afterstates: V(s') = w . phi(s') (+ b), scored for every placement at once."""

from __future__ import annotations

import torch
from torch import nn


class LinearValue(nn.Module):
    """A linear function of feature vectors, applied to the last dimension.

    With ``afterstate_features`` [B, A, F] it returns values [B, A]; a batch of
    weight vectors ``weight`` [B, F] (one policy per board) is supported through
    :func:`batched_values`.
    """

    def __init__(self, num_features: int, bias: bool = False) -> None:
        super().__init__()
        self.linear = nn.Linear(num_features, 1, bias=bias, dtype=torch.float64)
        nn.init.zeros_(self.linear.weight)
        if bias:
            nn.init.zeros_(self.linear.bias)

    @property
    def weight(self) -> torch.Tensor:
        return self.linear.weight.view(-1)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        return self.linear(features.to(self.linear.weight.dtype)).squeeze(-1)


def batched_values(weights: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """Values [B, A] of features [B, A, F] under one weight vector per board, ``weights`` [B, F]."""
    return torch.einsum("baf,bf->ba", features.to(weights.dtype), weights)


def greedy_placement(
    values: torch.Tensor, mask: torch.Tensor, terminal: torch.Tensor | None = None
) -> torch.Tensor:
    """Index of the best valid placement (the first on ties).

    Game-ending placements count only when every valid placement ends the game; then the best of
    them is taken (its lines still score).
    """
    keep = mask
    if terminal is not None:
        safe = mask & ~terminal
        keep = torch.where(safe.any(-1, keepdim=True), safe, mask)
    return values.masked_fill(~keep, -torch.inf).argmax(-1)
