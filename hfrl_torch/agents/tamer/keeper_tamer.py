"""TAMER for keepaway: H^(s, a) over tile coding, taught by one person watching a whole team.

Each field keeps its last ``history`` decisions (any keeper's): the active tiles of the action taken, which
H^ model it belongs to (one per team, or one per keeper), and when it started. Feedback at time t is spread
over the decisions of that field by a delay density (the thesis's gamma(2.0, 0.28) over the last 500 ms:
``feedback.credit.credit_weights``), so a press credits whichever keepers acted inside its window. Each
credited decision i moves its model by ``alpha / N * c_i * (h - H^(x_i))`` on its N active tiles (TAMER's
incremental rule with the tile-coding step size of Sarsa). The share of decisions that ever got credit is
counted (``credited`` / ``decisions``).
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.feedback.credit import CreditModel, GammaDelay, credit_weights
from hfrl_torch.models.tile_coding import TileCoding
from hfrl_torch.models.tile_coding_numba import compiled_add_, compiled_values

_PAST = -1e18


class KeeperTamer:
    """H^ for keepaway learners, batched over fields.

    :param model: the tile coding holding H^ (its learners: teams, or teams x keepers).
    :param fields: B, the fields watched (one person each, in a simulated experiment).
    :param alpha: step size, applied per tile as alpha / N (N active tiles of an action).
    :param credit: delay density of the credit (gamma(2.0, 0.28) by default).
    :param window: longest delay credited, seconds.
    :param history: decisions per field that can still receive credit.
    :param renormalise: scale each event's credits to sum to 1.
    :param kernels: ``"torch"`` (the reference, any device) or ``"numba"`` (H^'s sums and per-tile adds
        compiled, CPU only; the same weights within float32 rounding).
    """

    def __init__(
        self,
        model: TileCoding,
        fields: int,
        alpha: float = 0.125,
        credit: CreditModel | None = None,
        window: float | None = 0.5,
        history: int = 16,
        renormalise: bool = False,
        kernels: str = "torch",
    ) -> None:
        if kernels not in ("torch", "numba"):
            raise ValueError(f"KeeperTamer kernels={kernels!r} is invalid; allowed: torch, numba")
        if kernels == "numba" and model.weight.device.type != "cpu":
            raise ValueError(f"KeeperTamer kernels='numba' runs on the CPU only, not {model.weight.device}")
        if not alpha > 0 or history < 1 or fields < 1:
            raise ValueError(
                f"KeeperTamer needs alpha > 0, history >= 1, fields >= 1; got {alpha}, {history}, {fields}"
            )
        self.model = model
        self.alpha = float(alpha)
        self.credit = GammaDelay(2.0, 0.28) if credit is None else credit
        self.window = window
        self.renormalise = renormalise
        self.kernels = kernels
        n = model.active_tiles
        self.tiles = torch.zeros(fields, history, n, dtype=torch.int64)
        self.owner = torch.zeros(fields, history, dtype=torch.int64)
        self.starts = torch.full((fields, history), _PAST, dtype=torch.float64)
        self.filled = torch.zeros(fields, history, dtype=torch.bool)
        self.got_credit = torch.zeros(fields, history, dtype=torch.bool)
        self.decisions = 0
        self.credited = 0

    def values(self, owner: torch.Tensor, tiles: torch.Tensor) -> torch.Tensor:
        """H^ of every action ``[B, A]``: ``owner`` [B] (the model), ``tiles`` [B, A, N]."""
        if self.kernels == "numba":
            return compiled_values(self.model, owner, tiles)
        return self.model(owner, tiles)

    def record(
        self, deciding: torch.Tensor, owner: torch.Tensor, tiles: torch.Tensor, time: torch.Tensor
    ) -> None:
        """Remember the decisions of the fields flagged in ``deciding`` [B]: their model ``owner`` [B], the
        active tiles of the action taken ``tiles`` [B, N], at simulated ``time`` [B]."""
        d = deciding.to(torch.bool)
        retired = d & self.filled[:, 0]
        self.credited += int((self.got_credit[:, 0] & retired).sum())

        def roll(x: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
            shifted = torch.cat([x[:, 1:], new.unsqueeze(1)], 1)
            return torch.where(d.view(-1, *([1] * (x.dim() - 1))), shifted, x)

        self.tiles = roll(self.tiles, tiles.to(torch.int64))
        self.owner = roll(self.owner, owner.to(torch.int64))
        self.starts = roll(self.starts, time.to(torch.float64))
        self.filled = roll(self.filled, torch.ones_like(d))
        self.got_credit = roll(self.got_credit, torch.zeros_like(d))
        self.decisions += int(d.sum())

    def learn(self, feedback: TensorDictBase) -> int:
        """Learn from the feedback entries of ``feedback`` (``keys.FEEDBACK``, ``FEEDBACK_TIME``,
        ``FEEDBACK_MASK``, each [B, K]: the feedback channel's delivery), slot by slot, oldest first; returns
        how many decisions got credit."""
        given = feedback.get(keys.FEEDBACK_MASK).to(torch.bool).cpu()
        if not bool(given.any()):
            return 0
        value = torch.where(given, feedback.get(keys.FEEDBACK).to(torch.float64).cpu(), 0.0)
        when = torch.where(given, feedback.get(keys.FEEDBACK_TIME).to(torch.float64).cpu(), 0.0)
        slots = int(given.any(0).nonzero().max()) + 1
        return sum(self.give(value[:, k], when[:, k]) for k in range(slots))

    def give(self, values: torch.Tensor, times: torch.Tensor) -> int:
        """Learn from feedback ``values`` [B] (0: none) arriving at ``times`` [B]; returns how many decisions
        got credit."""
        given = values != 0
        if not bool(given.any()):
            return 0
        ends = torch.cat([self.starts[:, 1:], torch.full_like(self.starts[:, :1], torch.inf)], 1)
        c = credit_weights(
            times.to(torch.float64), self.starts, ends, self.credit, self.window, self.renormalise
        )
        c = torch.where(self.filled & given.unsqueeze(-1), c, 0.0)
        hit = c > 0
        if not bool(hit.any()):
            return 0
        rows, cols = hit.nonzero(as_tuple=True)
        owner, tiles = self.owner[rows, cols], self.tiles[rows, cols]
        compiled = self.kernels == "numba"
        if compiled:
            prediction = compiled_values(self.model, owner, tiles.unsqueeze(1)).squeeze(1).to(torch.float64)
        else:
            prediction = self.model(owner, tiles).to(torch.float64)
        error = values.to(torch.float64)[rows] - prediction
        step = (self.alpha / self.model.active_tiles) * c[rows, cols] * error
        if compiled:
            compiled_add_(self.model, owner, tiles, step)
        else:
            self.model.add_(owner, tiles, step.unsqueeze(-1).expand_as(tiles))
        self.got_credit[rows, cols] = True
        return int(hit.sum())

    @property
    def credited_share(self) -> float:
        """Share of the decisions (retired from the history) that received any credit."""
        retired = self.decisions - int(self.filled.sum())
        return self.credited / retired if retired > 0 else 0.0

    # --------------------------------------------------------------- checkpoints

    _HISTORY = ("tiles", "owner", "starts", "filled", "got_credit")

    def state_dict(self) -> dict[str, Any]:
        """H^'s weights, each field's decisions that can still receive credit, and the credit counts."""
        return {
            "weight": self.model.weight.clone(),
            **{k: getattr(self, k).clone() for k in self._HISTORY},
            "decisions": self.decisions,
            "credited": self.credited,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue the H^ and credit windows of :meth:`state_dict` (same fields, history and tiles)."""
        history = {k: state[k] for k in self._HISTORY}
        for k, v in history.items():
            now = getattr(self, k)
            if not isinstance(v, torch.Tensor) or v.shape != now.shape or v.dtype != now.dtype:
                raise ValueError(
                    f"KeeperTamer state {k!r} does not fit this one's {now.dtype} {tuple(now.shape)}"
                )
        self.model.weight.copy_(state["weight"])
        for k, v in history.items():
            setattr(self, k, v.clone())
        self.decisions, self.credited = int(state["decisions"]), int(state["credited"])
