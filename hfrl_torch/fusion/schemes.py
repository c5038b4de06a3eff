"""The fusion schemes, written once: how R and H^ are combined, at which level, and the arithmetic.

The thesis's rule is ``a = argmax_a f(R, H)`` (eq. 4.1), where R is the environment-trained estimate of every
action (the CE value of a Tetris afterstate, a Sarsa Q in keepaway, PG's logits) and H^ the TAMER model of the
person's reward. :func:`fuse_values` is ``f``. Each option of the ``fusion`` config group (:data:`OPTIONS`)
says which rule it applies at the decision (the values the action is chosen by) and which at the reward (what
the learner is trained on); :class:`~hfrl_torch.fusion.fusion.Fusion` applies them, and
:data:`COMPILED_RULES` gives the codes of the same rules to the compiled Tetris games.

Knox & Stone, "Combining Manual Feedback with Subsequent MDP Reward Signals for Reinforcement Learning"
(AAMAS 2010) and "Reinforcement Learning from Simultaneous Human and MDP Reward" (AAMAS 2012) name the
TAMER+RL techniques; reward shaping, action biasing and control sharing are offered here.
"""

from __future__ import annotations

import numbers
from typing import NamedTuple

import torch
from torch import Tensor

__all__ = [
    "COMPILED_RULES",
    "DECISION_SCHEMES",
    "FUSIONS",
    "OPTIONS",
    "REWARD_SCHEMES",
    "SCHEMES",
    "VALUE_SCHEMES",
    "Option",
    "Scheme",
    "fuse_values",
    "rescale_range",
    "signed_power",
]


class Scheme(NamedTuple):
    """A fusion rule's name and the levels it can act at.

    ``decision``: the values an action is chosen by; ``reward``: the reward the learner is trained on
    (``FeedbackFusion``).
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
]
DECISION_SCHEMES: tuple[str, ...] = tuple(s.name for s in SCHEMES if "decision" in s.levels)
REWARD_SCHEMES: tuple[str, ...] = tuple(s.name for s in SCHEMES if "reward" in s.levels)
VALUE_SCHEMES: tuple[str, ...] = tuple(s.name for s in SCHEMES if s.name != "control_sharing")
_ADDITIVE = ("linear", "action_biasing", "reward_shaping")


class Option(NamedTuple):
    """An option of the ``fusion`` config group: the rule at the decision and the rule at the reward."""

    decision: str
    reward: str


# the options of the ``fusion`` config group; ``annealed`` is the linear rule with Knox & Stone's annealed
# weight, ``action_biasing`` the linear sum used at selection only (the learner keeps its own Q)
OPTIONS: dict[str, Option] = {
    "none": Option("none", "none"),
    "human_only": Option("human_only", "none"),
    "linear": Option("linear", "none"),
    "exponential": Option("exponential", "none"),
    "annealed": Option("linear", "none"),
    "action_biasing": Option("linear", "none"),
    "control_sharing": Option("control_sharing", "none"),
    "reward_shaping": Option("none", "reward_shaping"),
}
FUSIONS: tuple[str, ...] = tuple(OPTIONS)

# codes of the decision rules inside compiled code (``fusion.compiled``)
COMPILED_RULES: dict[str, int] = {
    "none": 0,  # argmax R
    "human_only": 1,  # argmax H^
    "linear": 2,  # argmax R + w H^ (and the other additive rules)
    "exponential": 3,  # argmax R (1 + sign(H^) |H^|^w)
    "control_sharing": 4,  # argmax H^ with probability min(w, 1), else argmax R
}


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
    if not _broadcasts_to(w.shape, values.shape):
        raise ValueError(
            f"fusion weight of shape {tuple(weight.shape)} does not fit values {tuple(values.shape)}: "
            f"give one weight, or one per leading index (shape {tuple(values.shape[:-1])})"
        )
    return w


def _broadcasts_to(small: torch.Size, big: torch.Size) -> bool:
    """Whether ``small`` broadcasts to exactly ``big`` (``torch.broadcast_shapes`` costs 60 us a call)."""
    if len(small) > len(big):
        return False
    return all(s in (1, b) for s, b in zip(reversed(small), reversed(big), strict=False))


def fuse_values(
    env_values: Tensor, human_values: Tensor, scheme: str, weight: float | Tensor = 1.0
) -> Tensor:
    """Combine R and H^ for every action: ``f(R, H)`` of thesis eq. 4.1. Returns a new ``[..., A]`` tensor.

    :param env_values: R, ``[..., A]`` (e.g. ``[B, A]``: one value per board and placement).
    :param human_values: H^, same shape.
    :param scheme: one of ``VALUE_SCHEMES``:

        - ``none``: R; ``human_only``: H^;
        - ``linear`` (eq. 4.2), ``action_biasing``, ``reward_shaping``: ``R + w * H^``. Knox & Stone's
          techniques differ in *where* the sum is used (selection only, the reward), not in the
          arithmetic, so they share it under their own names;
        - ``exponential`` (eq. 5.1): ``R * (1 + sign(H^) * |H^| ** w)``, see :func:`signed_power`. The rule
          assumes R >= 0 (keepaway's hold times, lines): for R < 0 a larger factor makes the product more
          negative, so H^ acts with its sign reversed (a liked action is pushed down). Where
          ``sign(H^) |H^|^w < -1`` the factor is negative and flips the sign of R. With w = 0 the factor
          is ``1 + sign(H^)``: 2 for liked, 1 for neutral, 0 for disliked actions. For negative-valued
          estimates (CE afterstate values usually are) prefer ``linear``, or shift R to be >= 0.

        ``control_sharing`` is a selection rule, not a value: ``fusion.Fusion`` applies it.
    :param weight: ``w`` / ``beta`` >= 0: a number, or a tensor of shape ``[]`` or ``values.shape[:-1]``
        (one per board / learner).
    """
    if scheme not in VALUE_SCHEMES:
        hint = (
            "; control_sharing chooses whose values to follow: use Fusion"
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
