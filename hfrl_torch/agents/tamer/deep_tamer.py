"""Deep TAMER: a neural H^ trained from a TorchRL replay buffer of credited feedback (Warnell et al. 2018).

Warnell, Waytowich, Lawhern & Stone, "Deep TAMER: Interactive Agent Shaping in High-Dimensional State
Spaces" (AAAI 2018). Each decision of every board enters a short history (what H^ reads of it, the action
and when it was made). A feedback event h given at time t is credited to those decisions exactly as the
linear TAMER credits it (``feedback.credit.credit_weights``: the previous step in Tetris, the gamma delay
density over 500 ms in keepaway); every decision with credit c > 0 becomes one replay entry (input, action,
h, c), and c is its importance: H^ is fitted by Adam on the importance-weighted squared error
``sum c (H^(x, a) - h)^2 / sum c``. As in the paper, the entries of each new event are learned at once (one
step on them), and every ``replay_every`` loop steps one minibatch is drawn from the whole buffer, so old
feedback keeps shaping H^ while the states drift. The buffer is TorchRL's ``TensorDictReplayBuffer`` on a
``LazyTensorStorage`` with its own seeded generator, saved whole in checkpoints.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from torch import nn
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.feedback.credit import CreditModel, PreviousStep, credit_weights

__all__ = ["ENTRY_KEYS", "DeepTamer"]

_PAST = -1.0e12  # start time of an empty history slot
ENTRY_KEYS = ("inputs", "action", "feedback", "credit")  # what one replay entry holds


class DeepTamer:
    """H^ as a neural network over B boards that share it (one learner), fitted from credited feedback.

    :param model: the network: ``model(x_all)`` gives H^ of every action ``[B, A]``, ``model.select(x_all,
        action)`` what an entry keeps of a decision, ``model.chosen(x, action)`` H^ of stored entries
        (``models.mlp.AfterstateMLP`` or ``ActionMLP``).
    :param inputs: what H^ reads of a tensordict, ``[B, A, F]`` or ``[B, S]`` (e.g. placement deltas).
    :param boards: B.
    :param lr: Adam's step size.
    :param credit: credit model (``PreviousStep``, ``GammaDelay``, ``UniformDelay``).
    :param window: the longest delay credited, seconds (delay densities only).
    :param renormalise: scale each event's credits to sum to 1.
    :param history: decisions per board that can still receive credit.
    :param buffer_size: replay entries kept (the oldest are overwritten).
    :param batch_size: entries per replay minibatch.
    :param replay_every: loop steps between replay minibatches.
    :param seed: seed of the buffer's sampling.
    """

    def __init__(
        self,
        model: nn.Module,
        inputs: Callable[[TensorDictBase], torch.Tensor],
        boards: int,
        lr: float = 1e-3,
        credit: CreditModel | None = None,
        window: float | None = 0.5,
        renormalise: bool = False,
        history: int = 8,
        buffer_size: int = 10_000,
        batch_size: int = 32,
        replay_every: int = 10,
        seed: int = 0,
    ) -> None:
        if not (lr > 0 and boards >= 1 and history >= 1 and buffer_size >= 1 and batch_size >= 1):
            raise ValueError(
                "DeepTamer needs lr > 0, boards, history, buffer_size, batch_size >= 1; got "
                f"{lr}, {boards}, {history}, {buffer_size}, {batch_size}"
            )
        if replay_every < 1:
            raise ValueError(f"DeepTamer replay_every must be >= 1, got {replay_every}")
        self.model, self.inputs_of = model, inputs
        self.boards, self.history = int(boards), int(history)
        self.credit = PreviousStep() if credit is None else credit
        self.window, self.renormalise = window, bool(renormalise)
        self.batch_size, self.replay_every = int(batch_size), int(replay_every)
        self.optimizer = torch.optim.Adam(model.parameters(), lr=float(lr))
        self.buffer = TensorDictReplayBuffer(
            storage=LazyTensorStorage(int(buffer_size)),
            batch_size=self.batch_size,
            generator=torch.Generator().manual_seed(int(seed)),
        )
        self.x: torch.Tensor | None = None  # [B, N, D] what H^ reads of each recent decision
        self.actions = torch.zeros(self.boards, self.history, dtype=torch.int64)
        self.starts = torch.full((self.boards, self.history), _PAST, dtype=torch.float64)
        self.filled = torch.zeros(self.boards, self.history, dtype=torch.bool)
        self.steps = 0  # loop steps recorded
        self.applied = 0  # events learned from
        self.updates = 0  # Adam steps taken
        self.last_loss = float("nan")

    @torch.no_grad()
    def values(self, td: TensorDictBase) -> torch.Tensor:
        """H^ of every action ``[B, A]`` (float64)."""
        return self.model(self.inputs_of(td)).to(torch.float64)

    def record(
        self,
        td: TensorDictBase,
        action: torch.Tensor,
        time: torch.Tensor | float,
        active: torch.Tensor | None = None,
    ) -> None:
        """Remember each active board's decision ``action`` [B] in ``td`` made at ``time`` (seconds, [B] or
        one); every ``replay_every`` calls, one replay minibatch (once the buffer holds one)."""
        chosen = self.model.select(self.inputs_of(td), action.reshape(-1)).detach().cpu()
        if chosen.is_floating_point():  # frames keep their pixels' dtype (uint8: a quarter of the memory)
            chosen = chosen.to(torch.float32)
        if self.x is None:
            self.x = torch.zeros(self.boards, self.history, *chosen.shape[1:], dtype=chosen.dtype)
        act = torch.ones(self.boards, dtype=torch.bool) if active is None else active.reshape(-1).cpu().bool()
        now = torch.as_tensor(time, dtype=torch.float64).reshape(-1).expand(self.boards).cpu()
        a = act.view(-1, 1)
        kept = act.view(-1, 1, *[1] * (chosen.dim() - 1))
        self.x = torch.where(kept, torch.cat([self.x[:, 1:], chosen.unsqueeze(1)], 1), self.x)
        self.actions = torch.where(
            a, torch.cat([self.actions[:, 1:], action.reshape(-1, 1).cpu().to(torch.int64)], 1), self.actions
        )
        self.starts = torch.where(a, torch.cat([self.starts[:, 1:], now.unsqueeze(1)], 1), self.starts)
        self.filled = torch.where(a, torch.cat([self.filled[:, 1:], act.view(-1, 1)], 1), self.filled)
        self.steps += 1
        if self.steps % self.replay_every == 0 and len(self.buffer) >= self.batch_size:
            self.fit(self.buffer.sample())

    def credited(self, value: torch.Tensor, when: torch.Tensor, given: torch.Tensor) -> TensorDict:
        """The replay entries [M] of one event per board (``value``, ``when``, ``given``: [B]): every recent
        decision with credit > 0, its credit as importance."""
        ends = torch.cat([self.starts[:, 1:], torch.full((self.boards, 1), torch.inf)], dim=1)
        ends = torch.maximum(ends, self.starts)
        c = credit_weights(
            torch.where(given, when, 0.0), self.starts, ends, self.credit, self.window, self.renormalise
        )
        c = torch.where(self.filled & given.unsqueeze(-1), c, 0.0)
        rows, cols = (c > 0).nonzero(as_tuple=True)
        x = self.x if self.x is not None else torch.zeros(self.boards, self.history, 1)
        return TensorDict(
            {
                "inputs": x[rows, cols],
                "action": self.actions[rows, cols],
                "feedback": value[rows].to(torch.float32),
                "credit": c[rows, cols].to(torch.float32),
            },
            batch_size=[rows.numel()],
        )

    def learn(self, feedback: TensorDictBase) -> torch.Tensor:
        """Learn from the feedback entries of ``feedback`` (``keys.FEEDBACK``, ``FEEDBACK_TIME``,
        ``FEEDBACK_MASK``, each [B, K]), slot by slot, oldest first: credit, store, one step on the new
        entries. Returns the events learned per board [B]."""
        given = feedback.get(keys.FEEDBACK_MASK).to(torch.bool).cpu()
        if not bool(given.any()):
            return torch.zeros(self.boards, dtype=torch.int64)
        value = torch.where(given, feedback.get(keys.FEEDBACK).to(torch.float64).cpu(), 0.0)
        when = torch.where(given, feedback.get(keys.FEEDBACK_TIME).to(torch.float64).cpu(), 0.0)
        for k in range(int(given.any(0).nonzero().max()) + 1):
            entries = self.credited(value[:, k], when[:, k], given[:, k])
            if entries.numel():
                self.buffer.extend(entries)
                self.fit(entries)
        count = given.sum(-1).to(torch.int64)
        self.applied += int(count.sum())
        return count

    def fit(self, batch: TensorDictBase) -> float:
        """One Adam step on ``batch``'s importance-weighted squared error; returns the loss."""
        prediction = self.model.chosen(batch["inputs"], batch["action"])
        c = batch["credit"].to(prediction.dtype)
        loss = (c * (prediction - batch["feedback"].to(prediction.dtype)) ** 2).sum() / c.sum().clamp(
            min=1e-12
        )
        self.optimizer.zero_grad()
        loss.backward()
        self.optimizer.step()
        self.updates += 1
        self.last_loss = float(loss.detach())
        return self.last_loss

    def state_dict(self) -> dict[str, Any]:
        """The network, Adam's moments, the replay buffer, the recent decisions: what a resume continues."""
        return {
            "model": self.model.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "buffer": self.buffer.state_dict(),
            "x": None if self.x is None else self.x.clone(),
            "actions": self.actions.clone(),
            "starts": self.starts.clone(),
            "filled": self.filled.clone(),
            "counts": [self.steps, self.applied, self.updates],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; a malformed one raises ``CheckpointError``."""
        try:
            self.model.load_state_dict(state["model"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.buffer.load_state_dict(state["buffer"])
            storage = self.buffer.storage
            if getattr(storage, "initialized", False):  # a checkpoint keeps the entries, not their batch size
                storage._storage.auto_batch_size_(batch_dims=1)
            for k in ("actions", "starts", "filled"):
                if state[k].shape != getattr(self, k).shape:
                    raise ValueError(f"{k} of shape {tuple(state[k].shape)}")
                setattr(self, k, state[k].clone())
            self.x = None if state["x"] is None else state["x"].clone()
            self.steps, self.applied, self.updates = (int(v) for v in state["counts"])
        except (KeyError, TypeError, RuntimeError, ValueError, AttributeError) as e:
            raise CheckpointError(f"bad Deep TAMER state in the checkpoint ({e!r})") from None
