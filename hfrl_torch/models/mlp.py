"""Small neural value functions on TorchRL's ``MLP``: one value per placement's afterstate, or per action.

Two shapes of value the deep learners need (a DQN's Q and Deep TAMER's H^):

- :class:`AfterstateMLP` scores every placement of a Tetris decision from that placement's features,
  ``[..., A, F] -> [..., A]`` (one network applied to each afterstate, as the linear afterstate values are);
- :class:`ActionMLP` maps a state to one value per action, ``[..., S] -> [..., A]`` (keepaway's state
  variables to Hold and the passes).

Both scale their inputs by a fixed vector first (raw Tetris heights and keepaway distances and angles are tens
of units; a fixed scale keeps the first layer's inputs near 1 without a running statistic to save), and read
only the first ``used`` input columns, so a Q over the BT features can share the Knox features an H^ reads.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from torch import nn
from torchrl.modules import MLP

from hfrl_torch.models.tile_coding import keepaway_tile_widths

__all__ = ["ActionMLP", "AfterstateMLP"]


def _scale(scale: float | Sequence[float] | torch.Tensor, used: int) -> torch.Tensor:
    s = torch.as_tensor(scale, dtype=torch.float32).reshape(-1)
    if s.numel() == 1:
        s = s.expand(used).clone()
    if s.numel() != used or not bool(torch.isfinite(s).all()):
        raise ValueError(f"input scale needs one finite number or {used}, got {s.tolist()}")
    return s


class AfterstateMLP(nn.Module):
    """The value of each placement from its features: ``[..., A, F] -> [..., A]``.

    :param used: the input columns read (the first ``used`` of F).
    :param cells: hidden layer widths.
    :param scale: the inputs are multiplied by this (a number or one per used column).
    """

    def __init__(
        self, used: int, cells: Sequence[int] = (64, 64), scale: float | Sequence[float] = 1.0
    ) -> None:
        super().__init__()
        if used < 1:
            raise ValueError(f"AfterstateMLP needs used >= 1 input columns, got {used}")
        self.used = int(used)
        self.register_buffer("scale", _scale(scale, self.used))
        self.net = MLP(in_features=self.used, out_features=1, num_cells=list(cells), activation_class=nn.ReLU)

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        x = features[..., : self.used].to(self.scale.dtype) * self.scale
        return self.net(x).squeeze(-1)

    def chosen(self, inputs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The value ``[N]`` of stored chosen placements: ``inputs`` [N, F] are their features already."""
        return self(inputs.unsqueeze(-2)).squeeze(-1)

    @staticmethod
    def select(inputs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """What a replay entry keeps of a decision: the chosen placement's features ``[B, F]``."""
        index = action.reshape(-1, 1, 1).expand(-1, 1, inputs.shape[-1])
        return inputs.gather(-2, index).squeeze(-2)


class ActionMLP(nn.Module):
    """One value per action from the state: ``[..., S] -> [..., A]``.

    :param used: the input columns read (the first ``used`` of S).
    :param actions: A.
    :param cells: hidden layer widths.
    :param scale: the inputs are multiplied by this (a number or one per used column).
    """

    def __init__(
        self, used: int, actions: int, cells: Sequence[int] = (64, 64), scale: float | Sequence[float] = 1.0
    ) -> None:
        super().__init__()
        if used < 1 or actions < 1:
            raise ValueError(f"ActionMLP needs used >= 1 inputs and actions >= 1, got {used} and {actions}")
        self.used, self.actions = int(used), int(actions)
        self.register_buffer("scale", _scale(scale, self.used))
        self.net = MLP(
            in_features=self.used, out_features=self.actions, num_cells=list(cells), activation_class=nn.ReLU
        )

    def forward(self, state: torch.Tensor) -> torch.Tensor:
        return self.net(state[..., : self.used].to(self.scale.dtype) * self.scale)

    def chosen(self, inputs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """The value ``[N]`` of the stored states ``inputs`` [N, S] at the actions taken ``action`` [N]."""
        return self(inputs).gather(-1, action.reshape(-1, 1).to(torch.int64)).squeeze(-1)

    @staticmethod
    def select(inputs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """What a replay entry keeps of a decision: the state ``[B, S]`` (the action is stored beside it)."""
        return inputs


def keeper_scale(config: Any) -> list[float]:
    """Input scale of the keepers' networks: one over ten tile widths of each state variable (``config``: a
    ``KeepawayConfig``, its keepers and takers)."""
    return [1.0 / (10.0 * w) for w in keepaway_tile_widths(config.keepers, config.takers)]
