"""TAMER's model of the trainer's reward: H^(s, a) = w . phi(s, a), one weight vector per learner.

Knox & Stone, "Interactively Shaping Agents via Human Reinforcement" (K-CAP 2009); the thesis's
Algorithm 2. The model is linear and learned by incremental gradient descent with one step size.
"""

from __future__ import annotations

import torch
from torch import nn


class LinearRewardModel(nn.Module):
    """Linear reward model with a learner batch dimension: weights ``[L, F]`` (float64), starting at 0.

    Each learner l has its own weights, so B independent TAMER learners (one per board) are one module.

    :param num_features: length F of the feature vector phi.
    :param learners: number of independent learners L.

    Example:
        >>> m = LinearRewardModel(2, learners=1)
        >>> one = torch.ones(1, 1, dtype=torch.float64)
        >>> _ = m.update(torch.tensor([[[1.0, 2.0]]]), one, one, alpha=0.1)
        >>> m.weight.tolist()
        [[0.1, 0.2]]
    """

    def __init__(self, num_features: int, learners: int = 1) -> None:
        super().__init__()
        if num_features < 1 or learners < 1:
            raise ValueError(f"need num_features >= 1 and learners >= 1, got {num_features} and {learners}")
        self.weight = nn.Parameter(
            torch.zeros(learners, num_features, dtype=torch.float64), requires_grad=False
        )

    @property
    def learners(self) -> int:
        return self.weight.shape[0]

    @property
    def num_features(self) -> int:
        return self.weight.shape[1]

    def forward(self, phi: torch.Tensor) -> torch.Tensor:
        """Predicted reward ``[L, ...]`` of features ``phi`` ``[L, ..., F]`` (learner l's weights on row l)"""
        self._check(phi, "phi")
        x = phi.to(self.weight.dtype)
        w = self.weight.view(self.learners, *([1] * (x.dim() - 2)), self.num_features)
        return (x * w).sum(-1)

    @torch.no_grad()
    def update(self, phi: torch.Tensor, h: torch.Tensor, credit: torch.Tensor, alpha: float) -> torch.Tensor:
        """TAMER's incremental rule ``w += alpha * sum_i c_i (h_i - H^(phi_i)) phi_i``, per learner.

        ``phi`` ``[L, N, F]``, ``h`` and ``credit`` ``[L, N]``. Every H^ is taken with the weights before the
        update. Rows with credit 0, or without feedback (``h`` 0 or NaN: silence is not a label), change
        nothing. Returns the prediction errors ``h - H^`` ``[L, N]`` (0 on rows without feedback).
        """
        self._check(phi, "phi")
        if phi.dim() != 3 or h.shape != phi.shape[:2] or credit.shape != phi.shape[:2]:
            raise ValueError(
                f"update needs phi [L, N, F] and h, credit [L, N]; got {tuple(phi.shape)}, "
                f"{tuple(h.shape)}, {tuple(credit.shape)}"
            )
        x = phi.to(self.weight.dtype)
        h = h.to(self.weight.dtype)
        given = (h != 0) & ~torch.isnan(h) & (credit != 0)
        error = torch.where(given, h - self.forward(x), 0.0)
        c = torch.where(given, credit.to(self.weight.dtype), 0.0)
        self.weight += alpha * torch.einsum("ln,lnf->lf", c * error, x)
        return error

    def _check(self, phi: torch.Tensor, name: str) -> None:
        if phi.dim() < 2 or phi.shape[0] != self.learners or phi.shape[-1] != self.num_features:
            raise ValueError(
                f"{name} must be [L={self.learners}, ..., F={self.num_features}], got {tuple(phi.shape)}"
            )
