"""DQN (Mnih et al. 2015) assembled from TorchRL's parts: the Q network as a ``TensorDictModule``, greedy
choice by ``QValueModule`` over the choosable actions, ``torchrl.objectives.DQNLoss`` with a TD(0) target
from a target network kept by ``SoftUpdate``, and a ``TensorDictReplayBuffer`` on a ``LazyTensorStorage``.

Tetris scores afterstates: Q(s, a) is one network applied to the features of placement a's afterstate
(``models.mlp.AfterstateMLP``), so the target ``r + gamma max_a' Q(s', a')`` takes the max over the next
piece's choosable placements (valid, and not game-ending unless all are, ``fusion.choosable``). Keepaway has
one Q per action (``models.mlp.ActionMLP``). The network writes ``keys.ENV_VALUES``: the environment-trained
estimate the fusion component reads as R.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.modules import QValueModule
from torchrl.objectives import DQNLoss, SoftUpdate, ValueEstimators

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.fusion import choosable

__all__ = ["CHOOSABLE", "CHOSEN_VALUE", "DeepQ", "choosable_module"]

CHOOSABLE = "choosable"  # [B, A] bool: the actions a greedy choice may take (Tetris: not game-ending)
CHOSEN_VALUE = "chosen_action_value"  # TorchRL's key of the greedy action's value


def choosable_module() -> TensorDictModule:
    """Writes ``CHOOSABLE`` from a Tetris observation's action mask and game-ending placements."""
    return TensorDictModule(
        choosable, in_keys=[keys.ACTION_MASK, keys.AFTERSTATE_TERMINAL], out_keys=[CHOOSABLE]
    )


class DeepQ:
    """A DQN learner: its value network, loss, target, optimiser and replay buffer.

    :param model: the Q network (``AfterstateMLP`` or ``ActionMLP``).
    :param in_key: the observation it reads.
    :param mask_key: the mask of the actions the greedy choice and the target's max may take (None: all).
    :param pre: modules run before the network (Tetris: ``choosable_module()``).
    :param lr: Adam's step size.
    :param gamma: the discount per step.
    :param tau: the target network's soft-update rate (``SoftUpdate(eps=1 - tau)``).
    :param double: double DQN (the online network chooses the target's action).
    :param buffer_size: transitions kept.
    :param batch_size: transitions per update.
    :param seed: seed of the buffer's sampling.
    """

    def __init__(
        self,
        model: nn.Module,
        in_key: NestedKey,
        mask_key: NestedKey | None,
        pre: tuple[TensorDictModule, ...] = (),
        *,
        lr: float = 1e-3,
        gamma: float = 0.99,
        tau: float = 0.01,
        double: bool = True,
        buffer_size: int = 20_000,
        batch_size: int = 64,
        seed: int = 0,
    ) -> None:
        self.model = model
        self.q = TensorDictModule(model, in_keys=[in_key], out_keys=[keys.ENV_VALUES])
        self.pre = pre
        self.greedy = QValueModule(
            action_space="categorical",
            action_value_key=keys.ENV_VALUES,
            action_mask_key=mask_key,
            out_keys=[keys.ACTION, keys.ENV_VALUES, CHOSEN_VALUE],
        )
        self.value_network = TensorDictSequential(*pre, self.q, self.greedy)
        self.loss = DQNLoss(self.value_network, action_space="categorical", double_dqn=bool(double))
        self.loss.set_keys(action_value=keys.ENV_VALUES, value=CHOSEN_VALUE)
        self.loss.make_value_estimator(ValueEstimators.TD0, gamma=float(gamma))
        self.target = SoftUpdate(self.loss, eps=1.0 - float(tau))
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=float(lr))
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(int(buffer_size)),
            batch_size=int(batch_size),
            generator=torch.Generator().manual_seed(int(seed)),
        )
        self.updates = 0

    @property
    def stored_keys(self) -> list[NestedKey]:
        """What a transition in the buffer holds: the loss's inputs."""
        return list(self.loss.in_keys)

    def extend(self, data: TensorDictBase) -> None:
        """Store collected transitions (any batch shape; only the loss's inputs are kept)."""
        self.buffer.extend(data.reshape(-1).select(*self.stored_keys).to_tensordict())

    def update(self) -> float:
        """One step of the DQN loss on a minibatch, then the target's soft update; returns the loss."""
        loss = self.loss(self.buffer.sample())["loss"]
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        self.target.step()
        self.updates += 1
        return float(loss.detach())

    def state_dict(self) -> dict[str, Any]:
        """The online and target networks (the loss module's parameters) and Adam's moments. The replay
        buffer is not saved: tens of megabytes of transitions, refilled after a resume."""
        return {
            "loss": self.loss.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        try:
            self.loss.load_state_dict(state["loss"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.updates = int(state["updates"])
        except (KeyError, TypeError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"bad DQN state in the checkpoint ({e!r})") from None
