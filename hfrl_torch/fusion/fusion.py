"""The one fusion component: R and H^ combined for every learner, at the decision and at the reward.

:class:`Fusion` holds what fusing needs to remember: the weight schedule (trust factor, annealed or fixed),
the match count behind the trust (eqs. 4.3 and 4.4), the common scale of R and H^, and control sharing's
random draws. Every training loop and evaluation fuses through it, reading and writing tensordict keys:
``fuse`` takes ``keys.ENV_VALUES`` (CE's R, Sarsa's Q, PG's logits) and ``keys.HUMAN_VALUES`` (H^) of every
action and writes ``keys.FUSED_VALUES``, the values the action is chosen by; ``reward`` fuses a reward with
H^ for reward-level schemes; ``end_episode`` updates the weights. Its TorchRL faces are
:class:`~hfrl_torch.fusion.transform.FeedbackFusion` (a transform on the env, for the reward) and
:class:`~hfrl_torch.fusion.transform.FusionModule` (a module in the policy, for the decision); the
compiled Tetris games (:mod:`hfrl_torch.fusion.compiled`) take their rule and weights from it.

Scales: R and H^ may differ by orders of magnitude (CE values are hundreds, Q is in cycles, H^ about 1).
``scaling="decision"`` rescales both to [0, 1] over each decision's choosable actions; ``"spread"`` multiplies
H^ by the learner's running mean of max_a R - min_a R (H^ = 1 is then worth what R typically separates the
actions by; the exponential rule, which scales R by a factor of H^ alone, takes the raw values);
``"none"`` fuses the raw values.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from torch import Tensor

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.schedules import WeightSchedule
from hfrl_torch.fusion.schemes import (
    COMPILED_RULES,
    DECISION_SCHEMES,
    OPTIONS,
    REWARD_SCHEMES,
    fuse_values,
    rescale_range,
)
from hfrl_torch.fusion.trust import MatchCounter

__all__ = [
    "CONTROL_SHARING_THRESHOLD",
    "MIN_SPREAD",
    "SCALINGS",
    "Fusion",
    "changed_by_teaching",
    "choosable",
]

SCALINGS = ("none", "decision", "spread")
MIN_SPREAD = 1.0  # R units: H^ keeps a say before R has learned to separate the actions
CONTROL_SHARING_THRESHOLD = (
    0.5  # evaluation follows H^ where min(w, 1) >= this: the likelier side of the coin
)


def choosable(mask: Tensor, terminal: Tensor | None = None) -> Tensor:
    """The actions a greedy choice may take: valid, and not game-ending unless every valid one ends it."""
    if terminal is None:
        return mask
    safe = mask & ~terminal
    return torch.where(safe.any(-1, keepdim=True), safe, mask)


def changed_by_teaching(
    env_values: Tensor, action: Tensor, mask: Tensor, fused_values: Tensor | None = None
) -> Tensor:
    """[M] long: the action the environment's values alone [M, A] choose where they rate the one taken
    lower (the teaching changed the move), -1 elsewhere. With ``fused_values``, only where the taken action
    is also the fused values' best: an exploring move is not the teaching's."""
    env = env_values.masked_fill(~mask, -torch.inf)
    best = env.argmax(-1)
    taken = action.view(-1, 1)
    changed = env.gather(-1, best.view(-1, 1)).squeeze(-1) > env.gather(-1, taken).squeeze(-1) + 1e-9
    if fused_values is not None:
        fused = fused_values.masked_fill(~mask, -torch.inf)
        changed &= fused.gather(-1, taken).squeeze(-1) >= fused.amax(-1) - 1e-9
    return torch.where(changed, best, torch.full_like(best, -1))


class Fusion:
    """Fuse R and H^ for L learners: one decision rule, one reward rule, one weight schedule.

    :param decision: the rule the action is chosen by, one of ``DECISION_SCHEMES``.
    :param reward: the rule the learner's reward is fused by, one of ``REWARD_SCHEMES`` (``none``: the
        environment's reward).
    :param schedule: the weight w of each of the L learners.
    :param scaling: how R and H^ are put on one scale (see the module docstring).
    :param spread_rate: the step of the running mean of R's spread (``scaling="spread"``).
    :param seed: seed of control sharing's draws (one uniform per decision, whatever the weight).
    :param explore: whether a learner whose choice weighs H^ explores around it (its epsilon); ``False``: it
        chooses greedily on the fused values, as TAMER does (the Sarsa keepers under a bandit, whose weights
        are the exploration).
    """

    def __init__(
        self,
        decision: str,
        reward: str,
        schedule: WeightSchedule,
        *,
        scaling: str = "none",
        spread_rate: float = 0.01,
        seed: int = 0,
        explore: bool = True,
    ) -> None:
        if decision not in DECISION_SCHEMES:
            raise ValueError(f"decision rule {decision!r} is invalid; allowed: {', '.join(DECISION_SCHEMES)}")
        if reward not in REWARD_SCHEMES:
            raise ValueError(f"reward rule {reward!r} is invalid; allowed: {', '.join(REWARD_SCHEMES)}")
        if scaling not in SCALINGS:
            raise ValueError(f"scaling={scaling!r} is invalid; allowed: {', '.join(SCALINGS)}")
        if not 0.0 < spread_rate <= 1.0:
            raise ValueError(f"spread_rate must be in (0, 1], got {spread_rate!r}")
        self.decision, self.reward_rule, self.schedule = decision, reward, schedule
        self.scaling, self.spread_rate = scaling, float(spread_rate)
        self.explore = bool(explore)
        self.matches = MatchCounter(schedule.learners)
        self.q_spread = torch.full((schedule.learners,), MIN_SPREAD, dtype=torch.float64)
        self.generator = torch.Generator().manual_seed(int(seed))
        self.followed_human = 0
        self.evaluating = False

    @classmethod
    def from_option(cls, option: str, schedule: WeightSchedule, **kwargs: Any) -> Fusion:
        """The fusion of a ``fusion`` config option (``OPTIONS``: ``linear``, ``annealed``...)."""
        if option not in OPTIONS:
            raise ValueError(f"fusion={option!r} is invalid; allowed: {', '.join(OPTIONS)}")
        rules = OPTIONS[option]
        return cls(rules.decision, rules.reward, schedule, **kwargs)

    @property
    def learners(self) -> int:
        return self.schedule.learners

    @property
    def explores(self) -> bool:
        """Whether the learner explores around its choice: always on R alone, never for TAMER's human-only
        choice, and around a choice that weighs H^ unless ``explore`` is off."""
        return self.decision == "none" or (self.explore and self.decision != "human_only")

    @property
    def compiled_rule(self) -> int:
        """The decision rule's code in compiled games (``schemes.COMPILED_RULES``)."""
        return COMPILED_RULES[self.decision]

    def eval(self, evaluating: bool = True) -> Fusion:
        """Evaluation mode: nothing is counted or learned, and control sharing follows H^ exactly where
        min(w, 1) >= 0.5 (the likelier side of its coin), so a policy plays the same way every time."""
        self.evaluating = bool(evaluating)
        return self

    # ------------------------------------------------------------------ weights

    def weight(self, learner: Tensor | None = None, episodes: Tensor | None = None) -> Tensor:
        """The weight (float64) of each row's ``learner`` [M] (None: every learner, [L]); with ``episodes``
        (each row's episode index, learners along its first dimension) the schedule is read there."""
        if episodes is not None:
            return self.schedule.value(episodes).to(torch.float64)
        w = self.schedule.value().to(torch.float64).reshape(-1)
        return w if learner is None else w[learner.cpu()]

    def _learner(self, td: TensorDictBase) -> Tensor:
        learner = td.get(keys.LEARNER, None)
        if learner is not None:
            return learner.reshape(-1).cpu().to(torch.int64)
        rows = td.batch_size[0] if td.batch_dims else 1
        if self.learners == 1:
            return torch.zeros(rows, dtype=torch.int64)
        if rows == self.learners:
            return torch.arange(rows)
        raise ValueError(
            f"Fusion of {self.learners} learners got {rows} rows without a {keys.LEARNER!r} entry "
            "naming theirs"
        )

    # ----------------------------------------------------------------- decision

    def fuse(self, td: TensorDictBase, count: bool = True, weight: Tensor | None = None) -> TensorDictBase:
        """Write ``keys.FUSED_VALUES`` [M, A] and ``keys.FUSION_WEIGHT`` [M] into ``td``.

        Reads ``keys.ENV_VALUES`` and ``keys.HUMAN_VALUES`` [M, A], ``keys.ACTION_MASK`` (all valid if
        absent), ``keys.AFTERSTATE_TERMINAL`` (game-ending actions, if any) and ``keys.LEARNER`` [M] (whose
        weight; by default row m is learner m, or all rows learner 0). ``weight`` [M] replaces the
        schedule's weights. With ``count`` (and not evaluating), each decision goes into the match count of
        its learner.
        """
        h = td.get(keys.HUMAN_VALUES)
        r = td.get(keys.ENV_VALUES, None)
        if r is None:
            if self.decision != "human_only":
                raise KeyError(f"Fusion {self.decision!r} reads R from {keys.ENV_VALUES!r}, which is absent")
            r = torch.zeros_like(h)
        if r.shape != h.shape:
            raise ValueError(f"R and H^ differ in shape: {tuple(r.shape)} and {tuple(h.shape)}")
        mask = td.get(keys.ACTION_MASK, None)
        mask = torch.ones(h.shape, dtype=torch.bool, device=h.device) if mask is None else mask.to(torch.bool)
        terminal = td.get(keys.AFTERSTATE_TERMINAL, None)
        learner = self._learner(td)
        w = self.weight(learner) if weight is None else weight.reshape(-1).to(torch.float64).cpu()
        if count and not self.evaluating and keys.ENV_VALUES in td:
            self.matches.count(r, h, choosable(mask, terminal), learner)
        td.set(keys.FUSED_VALUES, self.values(r, h, mask, terminal, learner, w))
        td.set(keys.FUSION_WEIGHT, w.to(h.device))
        return td

    def values(
        self, r: Tensor, h: Tensor, mask: Tensor, terminal: Tensor | None, learner: Tensor, w: Tensor
    ) -> Tensor:
        """f(R, H^) [M, A] by the decision rule: what :meth:`fuse` writes (see it for the arguments)."""
        rule = self.decision
        if rule == "none":
            return r
        if rule == "human_only":
            return h
        if rule == "control_sharing":
            p = w.clamp(max=1.0).cpu()
            if self.evaluating:
                follow = p >= CONTROL_SHARING_THRESHOLD
            else:
                u = torch.rand(h.shape[0], generator=self.generator, dtype=torch.float64)
                follow = u < p
                self.followed_human += int(follow.sum())
            return torch.where(follow.to(h.device).unsqueeze(-1), h.to(torch.float64), r.to(torch.float64))
        if self.scaling == "decision":
            r, h = rescale_range(r, mask, terminal), rescale_range(h, mask, terminal)
        elif self.scaling == "spread" and rule != "exponential":
            spread = self.q_spread[learner] if self.evaluating else self._spread(learner, r, mask)
            r, h = r.to(torch.float64), h.to(torch.float64) * spread.to(h.device).unsqueeze(-1)
        return fuse_values(r, h, rule, w.to(r.device))

    def _spread(self, learner: Tensor, r: Tensor, mask: Tensor) -> Tensor:
        """Fold these decisions into each learner's running mean of R's spread; returns it per row."""
        q = r.detach().cpu().to(torch.float64)
        mk = mask.cpu()
        gap = q.masked_fill(~mk, -torch.inf).amax(-1) - q.masked_fill(~mk, torch.inf).amin(-1)
        choice = mk.sum(-1) > 1
        total = torch.zeros_like(self.q_spread).index_add_(0, learner[choice], gap[choice])
        count = torch.zeros_like(self.q_spread).index_add_(0, learner[choice], torch.ones_like(gap[choice]))
        seen = count > 0
        mean_gap = torch.where(seen, total / count.clamp(min=1), self.q_spread)
        moved = (1 - self.spread_rate) * self.q_spread + self.spread_rate * mean_gap
        self.q_spread = torch.where(seen, moved, self.q_spread).clamp(min=MIN_SPREAD)
        return self.q_spread[learner]

    # ------------------------------------------------------------------- reward

    def reward(self, reward: Tensor, human: Tensor, w: Tensor) -> Tensor:
        """The reward-level rule: f(r, H) with weights ``w`` (one per row, rows along the first dimension)."""
        if self.reward_rule == "none":
            return reward
        fused = fuse_values(reward, human.to(reward.device), self.reward_rule, w.to(reward.device))
        return fused.to(reward.dtype if reward.dtype.is_floating_point else torch.get_default_dtype())

    # ------------------------------------------------------------------ episodes

    def count_matches(self, learner: Tensor, matches: Tensor, compared: Tensor) -> None:
        """Add match counts made in compiled games (``fusion.compiled``) to the learners' episodes."""
        if not self.evaluating:
            self.matches.add(learner, matches, compared)

    def end_episode(
        self,
        ended: Tensor | None = None,
        performance: Tensor | float | None = None,
        taught: Tensor | None = None,
        *,
        compared: Tensor | None = None,
        searched: Tensor | None = None,
    ) -> None:
        """The flagged learners' episodes ended (bool [L]; None: all) with ``performance`` (lines, or hold
        time) and ``taught`` (bool [L]: the trainer gave feedback in them; None: not said): eq. 4.4 with their
        match rates for the trust factor, the episode's score for the bandit, one step for the annealed
        weight, ``compared`` (test games at :meth:`compared_weights`) for the paired comparison, ``searched``
        (the weight the learner's search settled on) for the searched weight; then the match counts restart.
        """
        flags = torch.ones(self.learners, dtype=torch.bool) if ended is None else ended.cpu().to(torch.bool)
        if taught is not None:
            self.schedule.taught(taught.cpu().to(torch.bool).reshape(-1).expand(self.learners), flags)
        perf = None
        if performance is not None:
            perf = torch.as_tensor(performance, dtype=torch.float64).reshape(-1).expand(self.learners)
        self.schedule.end_episode(perf, self.matches.rates(), flags, compared=compared, searched=searched)
        self.matches.reset(flags)

    def compared_weights(self) -> Tensor | None:
        """The weights [K] whose test games the learner passes back as ``end_episode(compared=...)``, on the
        same games; None: the weight needs no comparison."""
        return self.schedule.compared_weights()

    def weight_informed(self) -> bool:
        """Whether the weight rests on the run's own evidence yet (not on a comparison's first arm alone)."""
        return self.schedule.informed()

    @property
    def searches_weight(self) -> bool:
        """Whether the learner searches the weight itself and passes it as ``end_episode(searched=...)``."""
        return self.schedule.searched

    def describe_weight(self, score: str, episode: str) -> str:
        """What sets the weight, in plain words for the teaching page (see ``WeightSchedule.describe``)."""
        return self.schedule.describe(score, episode)

    def stats(self) -> dict[str, float]:
        """Means over learners of the weight and R's spread, for the logs."""
        return {
            "fusion/weight_mean": float(self.weight().mean()),
            "fusion/q_spread_mean": float(self.q_spread.mean()),
        }

    # ------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict[str, Any]:
        """The schedule, the match counts, R's spread and the draws, so a resumed run fuses the same way."""
        return {
            "schedule": self.schedule.state_dict(),
            "matches": self.matches.state_dict(),
            "q_spread": self.q_spread.clone(),
            "generator": self.generator.get_state(),
            "followed_human": self.followed_human,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; a malformed one raises ``CheckpointError``."""
        try:
            self.schedule.load_state_dict(state["schedule"])
            self.matches.load_state_dict(state["matches"])
            spread = state["q_spread"].to(torch.float64)
            self.generator.set_state(state["generator"])
            self.followed_human = int(state["followed_human"])
        except (KeyError, TypeError, AttributeError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"bad fusion state in the checkpoint ({e!r})") from None
        if spread.shape != self.q_spread.shape:
            raise CheckpointError(f"bad fusion state: {spread.numel()} spreads for {self.learners} learners")
        self.q_spread = spread.clone()

    def __repr__(self) -> str:
        return (
            f"Fusion(decision={self.decision!r}, reward={self.reward_rule!r}, schedule={self.schedule!r}, "
            f"scaling={self.scaling!r})"
        )
