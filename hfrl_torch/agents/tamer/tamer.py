"""TAMER for Tetris placements: learn a model H^ of the trainer's reward and act greedily on it.

Knox & Stone, "TAMER: Training an Agent Manually via Evaluative Reinforcement" (ICDL 2008) and
"Interactively Shaping Agents via Human Reinforcement" (K-CAP 2009); the thesis's Algorithms 1-3.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.feedback.credit import CreditModel, PreviousStep, credit_weights
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.models.linear import greedy_placement
from hfrl_torch.models.reward_model import LinearRewardModel

_PAST = -1.0e12  # start time of an empty history slot: long before any real step


def placement_deltas(obs: TensorDictBase) -> torch.Tensor:
    """phi(s, a) = f(afterstate of a) - f(s) for every placement: ``[B, A, F]`` float64."""
    after = obs[keys.AFTERSTATE_FEATURES].to(torch.float64)
    before = obs[keys.STATE_FEATURES].to(torch.float64)
    return after - before.unsqueeze(-2)


class TamerAgent:
    """TAMER in placement mode (Knox & Stone 2009; thesis Algorithms 1-3), one learner per board.

    H^(s, a) = w . phi(s, a) with phi the change of the board features caused by the whole placement,
    f(s') - f(s) (Knox's 46 features or the thesis's 21, whatever the env computes). Actions are greedy,
    argmax_a H^(s, a) over the valid placements, the first on ties and a game-ending placement only when
    every placement ends the game. Feedback events are held until the loop's clock passes their time,
    then credited to the recent placements by ``credit`` (all to the placement just completed with
    ``PreviousStep``, the Tetris default; ``GammaDelay`` / ``UniformDelay`` spread it by time) and
    learned with w += alpha * sum_i c_i (h - H^(phi_i)) phi_i, one event after another.

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
        self.pending: list[list[FeedbackEvent]] = [[] for _ in range(learners)]
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
        phi = placement_deltas(obs)
        chosen = phi.gather(1, action.view(-1, 1, 1).expand(-1, 1, phi.shape[-1])).squeeze(1)
        self.record_phi(chosen, time, active)

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

    def give_feedback(self, events: list[list[FeedbackEvent]], active: torch.Tensor | None = None) -> None:
        """Hold each learner's events (one list per board) until the clock passes their time."""
        for i, evs in enumerate(events):
            if active is None or bool(active[i]):
                self.pending[i].extend(evs)

    def learn(self, now: float) -> torch.Tensor:
        """Apply every held event with time <= ``now`` (Algorithm 2), oldest first; returns how many [L]."""
        due: list[list[FeedbackEvent]] = []
        for i in range(self.learners):
            evs = sorted(self.pending[i], key=lambda e: e.time)
            ready = [e for e in evs if e.time <= now]
            self.pending[i] = [e for e in evs if e.time > now]
            due.append(ready)
        rounds = max((len(d) for d in due), default=0)
        count = torch.tensor([len(d) for d in due], dtype=torch.int64)
        if rounds == 0:
            return count
        ends = torch.cat([self.starts[:, 1:], torch.full((self.learners, 1), torch.inf)], dim=1)
        ends = torch.maximum(ends, self.starts)
        for r in range(rounds):
            t = torch.tensor([d[r].time if r < len(d) else now for d in due], dtype=torch.float64)
            h = torch.tensor([d[r].value if r < len(d) else 0.0 for d in due], dtype=torch.float64)
            c = credit_weights(t, self.starts, ends, self.credit, self.window, self.renormalise)
            c = c * self.filled
            self.model.update(self.phi, h.unsqueeze(-1).expand_as(c), c, self.alpha)
        self.applied += count
        return count
