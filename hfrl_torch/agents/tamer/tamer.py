"""TAMER for Tetris placements: learn a model H^ of the trainer's reward and act greedily on it.

Knox & Stone, "TAMER: Training an Agent Manually via Evaluative Reinforcement" (ICDL 2008) and
"Interactively Shaping Agents via Human Reinforcement" (K-CAP 2009); the thesis's Algorithms 1-3.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.feedback.credit import CreditModel, PreviousStep, credit_weights
from hfrl_torch.models.linear import greedy_placement
from hfrl_torch.models.reward_model import LinearRewardModel

_PAST = -1.0e12  # start time of an empty history slot: long before any real step


def placement_deltas(obs: TensorDictBase, action: torch.Tensor | None = None) -> torch.Tensor:
    """phi(s, a) = f(afterstate of a) - f(s), float64: ``[B, A, F]`` for every placement, or ``[B, F]``
    for the placement ``action`` [B] of each board only."""
    after = obs[keys.AFTERSTATE_FEATURES]
    if action is not None:
        after = after.gather(1, action.view(-1, 1, 1).expand(-1, 1, after.shape[-1]))
    deltas = after.to(torch.float64) - obs[keys.STATE_FEATURES].to(torch.float64).unsqueeze(-2)
    return deltas if action is None else deltas.squeeze(1)


class TamerAgent:
    """TAMER in placement mode (Knox & Stone 2009; thesis Algorithms 1-3), one learner per board.

    H^(s, a) = w . phi(s, a) with phi the change of the board features caused by the whole placement,
    f(s') - f(s) (Knox's 46 features or the thesis's 21, whatever the env computes). Actions are greedy,
    argmax_a H^(s, a) over the valid placements, the first on ties and a game-ending placement only when
    every placement ends the game. Feedback comes as the tensordict entries of the feedback channel
    (``keys.FEEDBACK*``: the events due on the loop's clock, K slots per board); each event is credited to
    the recent placements by ``credit`` (all to the placement just completed with ``PreviousStep``, the
    Tetris default; ``GammaDelay`` / ``UniformDelay`` spread it by time) and learned with
    w += alpha * sum_i c_i (h - H^(phi_i)) phi_i, one event after another.

    :param num_features: F, the size of the env's feature set.
    :param learners: L, one independent learner per board of the env.
    :param alpha: the step size, TAMER's only tuned parameter.
    :param credit: credit model (``PreviousStep``, ``GammaDelay``, ``UniformDelay``).
    :param window: the longest delay credited, seconds (delay densities only; None = no limit).
    :param renormalise: scale each event's credits to sum to 1 (delay densities only).
    :param history: how many recent placements per learner can receive credit.
    """

    def __init__(
        self,
        num_features: int,
        learners: int,
        alpha: float,
        credit: CreditModel | None = None,
        window: float | None = 0.5,
        renormalise: bool = False,
        history: int = 8,
    ) -> None:
        if not alpha > 0:
            raise ValueError(f"TamerAgent alpha must be > 0, got {alpha!r}")
        if history < 1:
            raise ValueError(f"TamerAgent history must be >= 1, got {history!r}")
        self.model = LinearRewardModel(num_features, learners)
        self.alpha = float(alpha)
        self.credit = PreviousStep() if credit is None else credit
        self.window = window
        self.renormalise = renormalise
        self.phi = torch.zeros(learners, history, num_features, dtype=torch.float64)
        self.starts = torch.full((learners, history), _PAST, dtype=torch.float64)
        self.filled = torch.zeros(learners, history, dtype=torch.bool)
        self.applied = torch.zeros(learners, dtype=torch.int64)

    @property
    def learners(self) -> int:
        return self.model.learners

    def act(self, obs: TensorDictBase) -> torch.Tensor:
        """The greedy placement [B] under H^ (Algorithm 3)."""
        values = self.model(placement_deltas(obs))
        return greedy_placement(values, obs[keys.ACTION_MASK], obs[keys.AFTERSTATE_TERMINAL])

    def record(
        self, obs: TensorDictBase, action: torch.Tensor, time: float, active: torch.Tensor | None = None
    ) -> None:
        """Remember the placement each active learner makes at ``time`` (its phi), for credit."""
        self.record_phi(placement_deltas(obs, action), time, active)

    def record_phi(self, chosen: torch.Tensor, time: float, active: torch.Tensor | None = None) -> None:
        """Remember the features ``chosen`` [L, F] of the step each active learner takes at ``time``."""
        chosen = chosen.to(torch.float64)
        act = torch.ones(self.learners, dtype=torch.bool) if active is None else active.to(torch.bool)
        a = act.view(-1, 1)
        self.phi = torch.where(
            a.unsqueeze(-1), torch.cat([self.phi[:, 1:], chosen.unsqueeze(1)], 1), self.phi
        )
        now = torch.full((self.learners, 1), float(time), dtype=torch.float64)
        self.starts = torch.where(a, torch.cat([self.starts[:, 1:], now], 1), self.starts)
        self.filled = torch.where(a, torch.cat([self.filled[:, 1:], act.view(-1, 1)], 1), self.filled)

    def learn(self, feedback: TensorDictBase) -> torch.Tensor:
        """Learn from the feedback entries of ``feedback`` (``keys.FEEDBACK``, ``FEEDBACK_TIME``,
        ``FEEDBACK_MASK``, each [L, K]; Algorithm 2), slot by slot, oldest first; returns how many [L]."""
        given = feedback.get(keys.FEEDBACK_MASK).to(torch.bool)
        if not bool(given.any()):
            return torch.zeros(self.learners, dtype=torch.int64)
        value = feedback.get(keys.FEEDBACK).to(torch.float64)
        when = torch.where(given, feedback.get(keys.FEEDBACK_TIME).to(torch.float64), 0.0)
        count = given.sum(-1).cpu().to(torch.int64)
        slots = int(given.any(0).nonzero().max()) + 1
        ends = torch.cat([self.starts[:, 1:], torch.full((self.learners, 1), torch.inf)], dim=1)
        ends = torch.maximum(ends, self.starts)
        for k in range(slots):
            h = torch.where(given[:, k], value[:, k], 0.0).cpu()
            c = credit_weights(
                when[:, k].cpu(), self.starts, ends, self.credit, self.window, self.renormalise
            )
            c = c * self.filled
            self.model.update(self.phi, h.unsqueeze(-1).expand_as(c), c, self.alpha)
        self.applied += count
        return count

    def learner_state(self) -> dict[str, torch.Tensor]:
        """H^'s weights and the recent placements that can still get credit: what a resumed run continues."""
        return {
            "weight": self.model.weight.detach().clone(),
            "phi": self.phi.clone(),
            "starts": self.starts.clone(),
            "filled": self.filled.clone(),
            "applied": self.applied.clone(),
        }

    def load_learner_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore :meth:`learner_state`'s output (same learners, features and history)."""
        self.model.weight.copy_(state["weight"])
        for k in ("phi", "starts", "filled", "applied"):
            if state[k].shape != getattr(self, k).shape:
                raise ValueError(
                    f"TAMER state {k!r} of shape {tuple(state[k].shape)} for {tuple(getattr(self, k).shape)}"
                )
            setattr(self, k, state[k].clone())
