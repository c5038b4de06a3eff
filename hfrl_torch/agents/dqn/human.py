"""The H^ a deep learner fuses with, behind one face, whichever ``human=`` option models it.

A DQN learner plays B boards (fields) with one network, so its H^ is one model shared by its boards, each
board keeping its own recent decisions for credit. :class:`HumanValues` is what the learner asks of it:
H^ of every action, the record of each decision, learning from the feedback channel's entries, its state.
Deep TAMER (``agents.tamer.deep_tamer.DeepTamer``, ``human=mlp``) has it natively; the linear H^ of Tetris
(``human=linear``) and the tile-coded H^ of keepaway (``human=tile_coded``) are their TAMER agents as they
are, with the B boards' updates summed into one model (:class:`SharedLinearTamer`, :class:`SharedTileTamer`).
:class:`HumanValuesModule` and :class:`ChosenEstimate` put H^ on the policy's data path.
"""

from __future__ import annotations

from typing import Any, Protocol

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from hfrl_torch import keys
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.agents.tamer.tamer import TamerAgent, placement_deltas
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.models.tile_coding import TileCoding

__all__ = ["ChosenEstimate", "HumanValues", "HumanValuesModule", "SharedLinearTamer", "SharedTileTamer"]


class HumanValues(Protocol):
    """H^ as a deep learner uses it (one model shared by B boards)."""

    applied: int  # events learned from

    def values(self, td: TensorDictBase) -> torch.Tensor:
        """H^ of every action ``[B, A]``."""

    def record(
        self,
        td: TensorDictBase,
        action: torch.Tensor,
        time: torch.Tensor | float,
        active: torch.Tensor | None = None,
    ) -> None:
        """Remember each board's decision at ``time`` (seconds) for credit."""

    def learn(self, feedback: TensorDictBase) -> torch.Tensor:
        """Learn from the channel's entries ``[B, K]``; returns the events per board."""

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class SharedLinearTamer:
    """Tetris TAMER (``TamerAgent``, linear over placement deltas) with one weight vector for B boards.

    Each board keeps its history in the agent's learner rows; after each delivery the rows' updates are
    summed into the one model (every row starts equal), as B fields of one Sarsa learner sum theirs.
    """

    def __init__(self, agent: TamerAgent) -> None:
        self.agent = agent

    @property
    def applied(self) -> int:
        return int(self.agent.applied.sum())

    @property
    def weight(self) -> torch.Tensor:
        """The shared weights ``[F]``."""
        return self.agent.model.weight[0]

    @torch.no_grad()
    def values(self, td: TensorDictBase) -> torch.Tensor:
        return placement_deltas(td) @ self.weight.to(torch.float64)  # any number of boards (evaluation's too)

    def record(
        self,
        td: TensorDictBase,
        action: torch.Tensor,
        time: torch.Tensor | float,
        active: torch.Tensor | None = None,
    ) -> None:
        now = float(torch.as_tensor(time, dtype=torch.float64).reshape(-1)[0])  # one clock for every board
        self.agent.record(td, action.reshape(-1), now, active)

    @torch.no_grad()
    def learn(self, feedback: TensorDictBase) -> torch.Tensor:
        w = self.agent.model.weight
        before = w[0].clone()
        count = self.agent.learn(feedback)
        w.copy_((before + (w - before).sum(0)).expand_as(w))
        return count

    def state_dict(self) -> dict[str, Any]:
        return self.agent.learner_state()

    def load_state_dict(self, state: dict[str, Any]) -> None:
        try:
            self.agent.load_learner_state(state)
        except (KeyError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"bad TAMER state in the checkpoint ({e!r})") from None


class SharedTileTamer:
    """Keepaway TAMER (``KeeperTamer`` on a tile coding), one H^ for B fields (every decision's owner 0)."""

    def __init__(self, tamer: KeeperTamer) -> None:
        if tamer.model.learners != 1:
            raise ValueError(
                f"SharedTileTamer needs a tile coding of one learner, got {tamer.model.learners}"
            )
        self.tamer = tamer
        self.applied = 0

    @property
    def coder(self) -> TileCoding:
        return self.tamer.model

    def _tiles(self, td: TensorDictBase) -> torch.Tensor:
        return self.coder.tiles(td.get(keys.OBSERVATION).to(torch.float64))

    @torch.no_grad()
    def values(self, td: TensorDictBase) -> torch.Tensor:
        tiles = self._tiles(td)
        return self.tamer.values(torch.zeros(tiles.shape[0], dtype=torch.int64), tiles).to(torch.float64)

    def record(
        self,
        td: TensorDictBase,
        action: torch.Tensor,
        time: torch.Tensor | float,
        active: torch.Tensor | None = None,
    ) -> None:
        tiles = self._tiles(td)
        b = tiles.shape[0]
        taken = tiles[torch.arange(b), action.reshape(-1).to(torch.int64)]
        deciding = torch.ones(b, dtype=torch.bool) if active is None else active.reshape(-1).to(torch.bool)
        now = torch.as_tensor(time, dtype=torch.float64).reshape(-1).expand(b)
        self.tamer.record(deciding, torch.zeros(b, dtype=torch.int64), taken, now)

    def learn(self, feedback: TensorDictBase) -> torch.Tensor:
        given = feedback.get(keys.FEEDBACK_MASK).to(torch.bool).cpu()
        self.tamer.learn(feedback)
        count = given.sum(-1).to(torch.int64)
        self.applied += int(count.sum())
        return count

    def state_dict(self) -> dict[str, Any]:
        t = self.tamer
        return {
            "weight": t.model.weight.detach().clone(),
            "history": [
                t.tiles.clone(),
                t.owner.clone(),
                t.starts.clone(),
                t.filled.clone(),
                t.got_credit.clone(),
            ],
            "counts": [t.decisions, t.credited, self.applied],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        t = self.tamer
        try:
            t.model.weight.copy_(state["weight"])
            t.tiles, t.owner, t.starts, t.filled, t.got_credit = (x.clone() for x in state["history"])
            t.decisions, t.credited, self.applied = (int(x) for x in state["counts"])
        except (KeyError, TypeError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"bad keepaway TAMER state in the checkpoint ({e!r})") from None


class HumanValuesModule(TensorDictModuleBase):
    """A policy module writing ``keys.HUMAN_VALUES`` [B, A]: H^ of every action."""

    def __init__(self, human: HumanValues, in_keys: list[Any]) -> None:
        super().__init__()
        self.human = human
        self.in_keys, self.out_keys = list(in_keys), [keys.HUMAN_VALUES]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        tensordict.set(keys.HUMAN_VALUES, self.human.values(tensordict))
        return tensordict


class ChosenEstimate(TensorDictModuleBase):
    """A policy module writing ``keys.HUMAN_REWARD_ESTIMATE`` [B, 1]: H^ of the action taken (for shaping)."""

    def __init__(self) -> None:
        super().__init__()
        self.in_keys, self.out_keys = [keys.HUMAN_VALUES, keys.ACTION], [keys.HUMAN_REWARD_ESTIMATE]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        h = tensordict.get(keys.HUMAN_VALUES)
        action = tensordict.get(keys.ACTION).reshape(*h.shape[:-1], 1).to(torch.int64)
        tensordict.set(keys.HUMAN_REWARD_ESTIMATE, h.gather(-1, action).to(torch.float32))
        return tensordict
