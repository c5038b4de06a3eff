"""The kinds of weight on H^, in one table: each kind's config check, its construction and the evidence it
needs from the learner.

``fusion.weight`` names the kind: ``trust`` (the thesis's eq. 4.4), ``bandit``, ``paired``, ``search``, or
``adaptive`` (the best estimator the learner supports: ``paired`` for a learner that compares weights on the
same test games under a decision-level rule, else ``bandit``); a number is a ``constant`` weight.
``fusion=annealed`` anneals its own ``fusion.beta`` (``annealed``), and ``fusion=none`` and ``human_only``
use no weight: those three leave ``fusion.weight`` unused (:data:`WEIGHT_UNUSED`). A kind's
plain-words description is its schedule's :meth:`~hfrl_torch.fusion.schedules.WeightSchedule.describe`, and
its evidence arrives through :meth:`~hfrl_torch.fusion.fusion.Fusion.end_episode`, so nothing else reads
what a kind means.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.validation import require_float
from hfrl_torch.fusion.bandit import BanditWeight
from hfrl_torch.fusion.paired import PairedWeight
from hfrl_torch.fusion.schedules import (
    AnnealedWeight,
    ConstantWeight,
    SearchedWeight,
    TrustWeight,
    WeightSchedule,
)
from hfrl_torch.fusion.schemes import OPTIONS

__all__ = [
    "EVIDENCE",
    "UNWEIGHTED",
    "WEIGHT_KINDS",
    "WEIGHT_OPTIONS",
    "WEIGHT_UNUSED",
    "WeightKind",
    "check_weight",
    "make_weight",
    "weight_kind",
]

# what a learner does to give a kind's evidence beyond an episode's end (``Learner.weight_evidence``)
EVIDENCE = {
    "compared": "compares weights on the same test games",
    "searched": "searches the weight as part of its own search",
}
UNWEIGHTED = ("none", "human_only")  # fusion options that use no weight
WEIGHT_UNUSED = (*UNWEIGHTED, "annealed")  # options that leave fusion.weight unused (annealed: fusion.beta)


@dataclass(frozen=True)
class WeightKind:
    """One kind of weight: how ``fusion`` is checked for it and built into a schedule.

    :param name: the schedule's ``kind``.
    :param check: raises ``ConfigError`` on a bad value of ``fusion`` for this kind.
    :param build: the schedule of ``learners`` learners from a checked config.
    :param evidence: what the learner must give besides episode ends (a key of :data:`EVIDENCE`), if any;
        such a kind also needs a decision-level rule (a shaped reward would select a large weight).
    """

    name: str
    check: Callable[[DictConfig], None]
    build: Callable[[DictConfig, int], WeightSchedule]
    evidence: str | None = None


def _check_arms(cfg: DictConfig, key: str) -> list[float]:
    arms = OmegaConf.select(cfg, f"fusion.adaptive.{key}")
    values = list(arms) if OmegaConf.is_list(arms) else None
    if (
        values is None
        or len(values) < 2
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)
        or not all(math.isfinite(v) and v >= 0 for v in values)
        or len(set(values)) != len(values)
    ):
        raise ConfigError(
            f"fusion.adaptive.{key}={arms!r} is invalid; allowed: a list of two or more different "
            "weights >= 0"
        )
    return [float(v) for v in values]


def _check_adaptive(cfg: DictConfig) -> None:
    """``fusion.adaptive``, which every estimated kind reads (one block, so one sweep can switch kinds)."""
    if "adaptive" not in cfg.fusion:
        raise ConfigError(
            f"fusion.weight={cfg.fusion.weight} needs fusion.adaptive (arms, discount, prior_trust, "
            "prior_count, paired_arms, paired_discount, search_std)"
        )
    for key in ("arms", "paired_arms"):
        _check_arms(cfg, key)
    require_float(cfg, "fusion.adaptive.discount", 1e-6, 1.0)
    require_float(cfg, "fusion.adaptive.paired_discount", 0.0, 0.999)
    require_float(cfg, "fusion.adaptive.prior_trust", 0.0)
    require_float(cfg, "fusion.adaptive.prior_count", 1e-6)
    require_float(cfg, "fusion.adaptive.search_std", 1e-6)
    require_float(cfg, "fusion.initial_trust", 0.0)  # the search's first mean weight


def _check_constant(cfg: DictConfig) -> None:
    require_float(cfg, "fusion.weight", 0.0)


def _check_annealed(cfg: DictConfig) -> None:
    require_float(cfg, "fusion.beta", 0.0)
    require_float(cfg, "fusion.factor", 1e-9, 1.0)


def _check_trust(cfg: DictConfig) -> None:
    require_float(cfg, "fusion.initial_trust", 0.0, 1.0)  # a rate of agreement


def _bandit(cfg: DictConfig, learners: int) -> WeightSchedule:
    a = cfg.fusion.adaptive
    return BanditWeight(
        learners,
        list(a.arms),
        float(a.discount),
        prior_count=float(a.prior_count),
        prior_trust=float(a.prior_trust),
        seed=component_seed(cfg.seed, "bandit"),
    )


WEIGHT_KINDS: dict[str, WeightKind] = {
    k.name: k
    for k in (
        WeightKind(
            "constant", _check_constant, lambda cfg, n: ConstantWeight([float(cfg.fusion.weight)] * n)
        ),
        WeightKind(
            "annealed",
            _check_annealed,
            lambda cfg, n: AnnealedWeight([float(cfg.fusion.beta)] * n, float(cfg.fusion.factor)),
        ),
        WeightKind(
            "trust", _check_trust, lambda cfg, n: TrustWeight.from_initial(float(cfg.fusion.initial_trust), n)
        ),
        WeightKind("bandit", _check_adaptive, _bandit),
        WeightKind(
            "paired",
            _check_adaptive,
            lambda cfg, n: PairedWeight(
                n, list(cfg.fusion.adaptive.paired_arms), float(cfg.fusion.adaptive.paired_discount)
            ),
            evidence="compared",
        ),
        WeightKind(
            "search",
            _check_adaptive,
            lambda cfg, n: SearchedWeight([float(cfg.fusion.initial_trust)] * n),
            evidence="searched",
        ),
    )
}
# the words fusion.weight takes besides a number
WEIGHT_OPTIONS: tuple[str, ...] = ("trust", "adaptive", "bandit", "paired", "search")


def _bad_option(weight: object) -> ConfigError:
    return ConfigError(
        f"fusion.weight={weight!r} is invalid; allowed: {', '.join(WEIGHT_OPTIONS)}, or a number >= 0"
    )


def weight_kind(cfg: DictConfig, evidence: Collection[str] = ()) -> str:
    """The kind of weight ``fusion`` asks of a learner that gives ``evidence`` (keys of :data:`EVIDENCE`):
    ``adaptive`` becomes ``paired`` where the learner compares weights under a decision-level rule, else
    ``bandit``; a number is ``constant``; ``fusion=annealed`` is ``annealed``."""
    name = str(cfg.fusion.name)
    if name in UNWEIGHTED:
        return "constant"
    if name == "annealed":
        return "annealed"
    weight = OmegaConf.select(cfg, "fusion.weight")
    if not isinstance(weight, str):
        return "constant"
    if weight == "adaptive":
        decision_level = OPTIONS[name].reward == "none"
        return "paired" if "compared" in evidence and decision_level else "bandit"
    if weight not in WEIGHT_OPTIONS:
        raise _bad_option(weight)
    return weight


def check_weight(
    cfg: DictConfig, evidence: Collection[str] = (), givers: Mapping[str, Sequence[str]] | None = None
) -> None:
    """Check ``fusion``'s weight for a learner that gives ``evidence``; ``givers`` names, for the error, the
    agents that give each kind of evidence. Raises ``ConfigError`` with one line."""
    name = str(cfg.fusion.name)
    weight = OmegaConf.select(cfg, "fusion.weight", default="adaptive")
    if name in WEIGHT_UNUSED:  # fusion.weight is unused; still one of the allowed kinds (sweeps set it)
        if not isinstance(weight, str):
            _check_constant(cfg)
        elif weight not in WEIGHT_OPTIONS:
            raise _bad_option(weight)
    if name in UNWEIGHTED:
        return
    kind = WEIGHT_KINDS[weight_kind(cfg, evidence)]
    needed = kind.evidence
    if needed is not None and (needed not in evidence or OPTIONS[name].reward != "none"):
        agents = ", ".join(f"agent={a}" for a in (givers or {}).get(needed, ()))
        decision = ", ".join(
            o for o, rules in OPTIONS.items() if rules.reward == "none" and o not in WEIGHT_UNUSED
        )
        raise ConfigError(
            f"fusion.weight={weight} with agent={cfg.agent.name} fusion={name} is invalid: it needs a "
            f"learner that {EVIDENCE[needed]} ({agents or 'none here'}) and a decision-level rule "
            f"(fusion={decision}); use adaptive or bandit"
        )
    kind.check(cfg)


def make_weight(cfg: DictConfig, learners: int = 1, evidence: Collection[str] = ()) -> WeightSchedule:
    """The weight schedule of ``fusion`` for ``learners`` learners giving ``evidence`` (a checked config)."""
    if str(cfg.fusion.name) in UNWEIGHTED:
        return ConstantWeight([0.0] * learners)
    return WEIGHT_KINDS[weight_kind(cfg, evidence)].build(cfg, learners)
