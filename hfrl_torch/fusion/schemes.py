"""Decision-level fusion: combine the environment-trained values R and the person's model H^ into one choice.

The thesis's rule is ``a = argmax_a f(R, H)`` (eq. 4.1), where R is the environment-trained estimate of every
action (the CE value of a Tetris afterstate, a Sarsa Q in keepaway) and H^ the TAMER model of the person's
reward. :func:`fuse_values` is ``f``; :class:`FusedActionSelector` takes the argmax (or, for control
sharing, picks whose argmax to follow). Reward-level fusion, which changes the reward the learner sees,
lives in :class:`hfrl_torch.fusion.transform.FeedbackFusion`.

Knox & Stone, "Combining Manual Feedback with Subsequent MDP Reward Signals for Reinforcement Learning"
(AAMAS 2010) and "Reinforcement Learning from Simultaneous Human and MDP Reward" (AAMAS 2012) name the
TAMER+RL techniques offered here: reward shaping, Q augmentation, action biasing and control sharing.
"""

from __future__ import annotations

import numbers
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor, nn

from hfrl_torch.fusion.schedules import WeightSchedule, as_schedule
from hfrl_torch.models.linear import greedy_placement

__all__ = [
    "DECISION_SCHEMES",
    "FUSIONS",
    "REWARD_SCHEMES",
    "SCHEMES",
    "TARGET_SCHEMES",
    "VALUE_SCHEMES",
    "FusedActionSelector",
    "Scheme",
    "fuse_values",
    "rescale_range",
    "signed_power",
]


class Scheme(NamedTuple):
    """A fusion scheme's name and the levels it acts at.

    ``decision``: how an action is chosen from R and H^ (:class:`FusedActionSelector`); ``reward``: the
    reward the learner is trained on (``FeedbackFusion``); ``target``: the value inside the learner's update
    target (``max_a' fuse_values(Q(s'), H^(s'), "q_augmentation", beta)``, for an agent to use).
    """

    name: str
    levels: tuple[str, ...]
    summary: str


SCHEMES: list[Scheme] = [
    Scheme("none", ("decision", "reward"), "environment only: R"),
    Scheme("human_only", ("decision", "reward"), "H^ only (TAMER): H"),
    Scheme("linear", ("decision", "reward"), "R + w H (thesis eq. 4.2)"),
    Scheme("exponential", ("decision", "reward"), "R (1 + sign(H) |H|^w) (thesis eq. 5.1)"),
    Scheme("action_biasing", ("decision",), "Q + beta H at selection only (Knox & Stone)"),
    Scheme("control_sharing", ("decision",), "follow argmax H with probability min(beta, 1) (Knox & Stone)"),
    Scheme("reward_shaping", ("reward",), "R' = R + beta H (Knox & Stone)"),
    Scheme("q_augmentation", ("target",), "Q + beta H in the update target (Knox & Stone)"),
]

# the options of the ``fusion`` config group (``annealed`` is the linear rule with an annealed weight)
FUSIONS: tuple[str, ...] = (
    "none",
    "human_only",
    "linear",
    "exponential",
    "annealed",
    "action_biasing",
    "control_sharing",
    "reward_shaping",
)
DECISION_SCHEMES: tuple[str, ...] = tuple(s.name for s in SCHEMES if "decision" in s.levels)
REWARD_SCHEMES: tuple[str, ...] = tuple(s.name for s in SCHEMES if "reward" in s.levels)
TARGET_SCHEMES: tuple[str, ...] = tuple(s.name for s in SCHEMES if "target" in s.levels)
VALUE_SCHEMES: tuple[str, ...] = tuple(s.name for s in SCHEMES if s.name != "control_sharing")
_ADDITIVE = ("linear", "action_biasing", "reward_shaping", "q_augmentation")


def signed_power(h: Tensor, w: Tensor) -> Tensor:
    """``sign(h) * |h| ** w``: the thesis's ``H ** w`` made defined for negative H and non-integer w.

    It equals ``H ** w`` wherever that is real and positive-based, keeps the sign of H (a disliked action
    stays disliked) and is odd in H. ``h = 0`` gives 0 for every w, including w = 0.
    """
    return torch.sign(h) * torch.pow(h.abs(), w)


def _weight_tensor(weight: float | Tensor, values: Tensor) -> Tensor:
    if isinstance(weight, numbers.Real) and not isinstance(weight, bool):
        if not (float(weight) >= 0 and float(weight) < float("inf")):
            raise ValueError(f"fusion weight must be finite and >= 0, got {weight!r}")
        return torch.tensor(float(weight), dtype=values.dtype, device=values.device)
    if not isinstance(weight, Tensor):
        raise TypeError(f"fusion weight must be a number or a tensor, got {type(weight).__name__}")
    w = weight.to(dtype=values.dtype, device=values.device)
    if w.ndim:
        w = w.unsqueeze(-1)
    try:
        shape = torch.broadcast_shapes(w.shape, values.shape)
    except RuntimeError:
        shape = None
    if shape != values.shape:
        raise ValueError(
            f"fusion weight of shape {tuple(weight.shape)} does not fit values {tuple(values.shape)}: "
            f"give one weight, or one per leading index (shape {tuple(values.shape[:-1])})"
        )
    return w


def fuse_values(
    env_values: Tensor, human_values: Tensor, scheme: str, weight: float | Tensor = 1.0
) -> Tensor:
    """Combine R and H^ for every action: ``f(R, H)`` of thesis eq. 4.1. Returns a new ``[..., A]`` tensor.

    :param env_values: R, ``[..., A]`` (e.g. ``[B, A]``: one value per board and placement).
    :param human_values: H^, same shape.
    :param scheme: one of ``VALUE_SCHEMES``:

        - ``none``: R; ``human_only``: H^;
        - ``linear`` (eq. 4.2), ``action_biasing``, ``reward_shaping``, ``q_augmentation``: ``R + w * H^``.
          Knox & Stone's techniques differ in *where* the sum is used (selection only, the reward, the
          update target), not in the arithmetic, so they share it under their own names;
        - ``exponential`` (eq. 5.1): ``R * (1 + sign(H^) * |H^| ** w)``, see :func:`signed_power`. The rule
          assumes R >= 0 (keepaway's hold times, lines): for R < 0 a larger factor makes the product more
          negative, so H^ acts with its sign reversed (a liked action is pushed down). Where
          ``sign(H^) |H^|^w < -1`` the factor is negative and flips the sign of R. With w = 0 the factor
          is ``1 + sign(H^)``: 2 for liked, 1 for neutral, 0 for disliked actions. For negative-valued
          estimates (CE afterstate values usually are) prefer ``linear``, or shift R to be >= 0.

        ``control_sharing`` is a selection rule, not a value: use :class:`FusedActionSelector`.
    :param weight: ``w`` / ``beta`` >= 0: a number, or a tensor of shape ``[]`` or ``values.shape[:-1]``
        (one per board / learner).
    """
    if scheme not in VALUE_SCHEMES:
        hint = (
            "; control_sharing chooses actions: use FusedActionSelector"
            if scheme == "control_sharing"
            else ""
        )
        raise ValueError(f"scheme={scheme!r} is invalid; allowed: {', '.join(VALUE_SCHEMES)}{hint}")
    if env_values.shape != human_values.shape:
        raise ValueError(
            f"env_values and human_values differ in shape: {tuple(env_values.shape)} and "
            f"{tuple(human_values.shape)}"
        )
    dtype = torch.promote_types(env_values.dtype, human_values.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    r = env_values.to(dtype)
    h = human_values.to(dtype=dtype, device=r.device)
    if scheme == "none":
        return r.clone()
    if scheme == "human_only":
        return h.clone()
    w = _weight_tensor(weight, r)
    if scheme in _ADDITIVE:
        return r + w * h
    return r * (1.0 + signed_power(h, w))


def rescale_range(values: Tensor, mask: Tensor, terminal: Tensor | None = None) -> Tensor:
    """``(v - min) / (max - min)`` over each row's choosable actions, ``[..., A]`` float64 (0: all equal).

    Choosable: valid, and not game-ending unless every valid action ends the game (the greedy rule). R (CE
    afterstate values, hundreds) and H^ (feedback units, about 1) differ in scale by orders of magnitude; on
    a common [0, 1] scale a weight w in ``R + w H^`` says how much H^ counts next to R, which is what a
    trust factor in [0, 1] means. Actions outside the choosable set may fall outside [0, 1].
    """
    keep = mask
    if terminal is not None:
        safe = mask & ~terminal
        keep = torch.where(safe.any(-1, keepdim=True), safe, mask)
    v = values.to(torch.float64)
    lo = v.masked_fill(~keep, torch.inf).amin(-1, keepdim=True)
    hi = v.masked_fill(~keep, -torch.inf).amax(-1, keepdim=True)
    span = hi - lo
    ok = span > 0
    return torch.where(ok, (v - lo) / torch.where(ok, span, 1.0), 0.0)


class FusedActionSelector(nn.Module):
    """Choose one action per board from R and H^ under a decision-level scheme (thesis eq. 4.1).

    Value schemes (``none``, ``human_only``, ``linear``, ``exponential``, ``action_biasing``) take
    ``greedy_placement(fuse_values(R, H^))``: the best valid action, the first on ties, a game-ending one only
    when every valid action ends the game. ``control_sharing`` (Knox & Stone 2010) follows, on each board
    independently, ``argmax H^`` with probability ``min(beta, 1)`` and ``argmax R`` otherwise (each argmax
    by the same greedy rule). It draws one uniform number per board on every call, whatever beta is, from
    its own generator, so the choices are a function of the seed and the call sequence.

    :param scheme: one of ``DECISION_SCHEMES``.
    :param weight: ``w`` / ``beta``: a number, one number per board, or a :class:`WeightSchedule`.
    :param generator: the random source of control sharing (CPU); None: a fresh one seeded with 0.
    :param normalise: rescale R and H^ to [0, 1] over each board's choosable actions before fusing them
        (:func:`rescale_range`; ``linear``, ``exponential`` and ``action_biasing``).

    After each call, ``last_followed_human`` (bool, one per board) says which boards followed H^'s argmax
    (control sharing), or is None for the other schemes.
    """

    def __init__(
        self,
        scheme: str,
        weight: float | Sequence[float] | Tensor | WeightSchedule = 1.0,
        generator: torch.Generator | None = None,
        normalise: bool = False,
    ) -> None:
        super().__init__()
        if scheme not in DECISION_SCHEMES:
            raise ValueError(
                f"FusedActionSelector scheme={scheme!r} is invalid; allowed: {', '.join(DECISION_SCHEMES)}"
            )
        self.scheme = scheme
        self.schedule = as_schedule(weight)
        self.generator = generator if generator is not None else torch.Generator().manual_seed(0)
        self.normalise = normalise
        self.last_followed_human: Tensor | None = None

    def weight(self, episode: int | Tensor | None = None) -> Tensor:
        """The weight at ``episode`` (None: the schedule's own episode count)."""
        return self.schedule.value(episode)

    def forward(
        self,
        env_values: Tensor,
        human_values: Tensor,
        mask: Tensor | None = None,
        terminal: Tensor | None = None,
        episode: int | Tensor | None = None,
    ) -> Tensor:
        """The chosen action index per board, ``[B]`` (int64).

        :param env_values: R, ``[B, A]``.
        :param human_values: H^, ``[B, A]``.
        :param mask: bool ``[B, A]``, the valid actions (None: all).
        :param terminal: bool ``[B, A]``, actions that end the game (avoided unless all valid ones do).
        :param episode: each board's episode index for the weight schedule (None: its own count).
        """
        if env_values.shape != human_values.shape:
            raise ValueError(
                f"env_values and human_values differ in shape: {tuple(env_values.shape)} and "
                f"{tuple(human_values.shape)}"
            )
        if mask is None:
            mask = torch.ones(env_values.shape, dtype=torch.bool, device=env_values.device)
        w = self.weight(episode)
        if self.scheme != "control_sharing":
            self.last_followed_human = None
            r, h = env_values, human_values
            if self.normalise and self.scheme not in ("none", "human_only"):
                r, h = rescale_range(r, mask, terminal), rescale_range(h, mask, terminal)
            return greedy_placement(fuse_values(r, h, self.scheme, w), mask, terminal)
        by_env = greedy_placement(env_values, mask, terminal)
        by_human = greedy_placement(human_values, mask, terminal)
        u = torch.rand(
            by_env.shape, generator=self.generator, dtype=torch.float64, device=self.generator.device
        )
        p = w.to(torch.float64).clamp(max=1.0)
        try:
            follow = (u < p.to(u.device)).to(by_env.device)
        except RuntimeError:
            raise ValueError(
                f"control_sharing weight of shape {tuple(p.shape)} does not fit {by_env.numel()} boards"
            ) from None
        if follow.shape != by_env.shape:
            raise ValueError(
                f"control_sharing weight of shape {tuple(p.shape)} does not fit boards {tuple(by_env.shape)}"
            )
        self.last_followed_human = follow
        return torch.where(follow, by_human, by_env)

    def get_extra_state(self) -> dict[str, Any]:
        """The schedule's state and the generator's, so a resumed run draws the same numbers."""
        return {"schedule": self.schedule.state_dict(), "generator": self.generator.get_state()}

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.schedule.load_state_dict(state["schedule"])
        self.generator.set_state(state["generator"])

    def extra_repr(self) -> str:
        return f"scheme={self.scheme!r}, weight={self.schedule!r}, normalise={self.normalise}"
