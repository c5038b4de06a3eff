"""The registries ``train.py`` and ``evaluate.py`` dispatch through: the domains, and the learner of each
agent on each domain. A domain or a learner added from outside the package registers itself here
(:func:`register_domain`, :func:`register_learner`); nothing else in ``experiment/`` names one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from omegaconf import DictConfig

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.validation import require_choice
from hfrl_torch.experiment.checks import (
    check_gym_domain,
    check_gym_evaluation,
    check_keepaway_domain,
    check_keepaway_evaluation,
    check_tetris_domain,
    check_tetris_evaluation,
)
from hfrl_torch.experiment.gym_evaluation import evaluate_gym, format_gym_summary
from hfrl_torch.experiment.keepaway_evaluation import evaluate_keepaway, format_keepaway_summary
from hfrl_torch.experiment.learners.gym_dqn import GymDQN
from hfrl_torch.experiment.learners.gym_ppo import GymPPO
from hfrl_torch.experiment.learners.gym_tamer import GymTamer
from hfrl_torch.experiment.learners.keepaway_dqn import KeepawayDQN
from hfrl_torch.experiment.learners.keepaway_sarsa import SarsaKeepers
from hfrl_torch.experiment.learners.tetris_cem import CEMLearner
from hfrl_torch.experiment.learners.tetris_dqn import TetrisDQN
from hfrl_torch.experiment.learners.tetris_pg import PolicyGradientLearner
from hfrl_torch.experiment.learners.tetris_qlearning import QLearningLearner
from hfrl_torch.experiment.learners.tetris_tamer import TamerLearner
from hfrl_torch.experiment.run import Learner
from hfrl_torch.experiment.tetris_evaluation import evaluate_tetris, format_summary


@dataclass(frozen=True)
class Domain:
    """A task ``train.py`` and ``evaluate.py`` run (``domain=<name>``, ``conf/domain/<name>.yaml``).

    :param name: ``domain.name``.
    :param check: raises ``ConfigError`` on a bad value of the ``domain`` group.
    :param check_evaluate: the same for ``evaluate.py`` (its own options included).
    :param evaluate: ``evaluate.py``'s play of ``policy`` on this domain; returns the JSON summary.
    :param summary: the human-readable lines printed above that JSON.
    :param default_agent: the agent ``conf/agent/default_<name>.yaml`` picks.
    :param spread: whether ``fusion.normalise=spread`` (H^ times Q's running spread) is an option here.
    """

    name: str
    check: Callable[[DictConfig], None]
    check_evaluate: Callable[[DictConfig], None]
    evaluate: Callable[[DictConfig], dict[str, object]]
    summary: Callable[[dict[str, object]], str]
    default_agent: str
    spread: bool = False


DOMAINS: dict[str, Domain] = {}
LEARNERS: dict[tuple[str, str], type[Learner]] = {}  # (domain, agent) -> learner class


def register_domain(domain: Domain) -> Domain:
    """Make ``domain=<domain.name>`` known to ``train.py`` and ``evaluate.py``; returns it."""
    if domain.name in DOMAINS and DOMAINS[domain.name] != domain:
        raise ValueError(f"domain {domain.name!r} is registered already")
    DOMAINS[domain.name] = domain
    return domain


def register_learner(learner: type[Learner]) -> type[Learner]:
    """Make ``agent=<learner.agent>`` on ``domain=<learner.domain>`` run ``learner`` (a class decorator)."""
    key = (learner.domain, learner.agent)
    if key in LEARNERS and LEARNERS[key] is not learner:
        raise ValueError(f"agent {learner.agent!r} on domain {learner.domain!r} has a learner already")
    LEARNERS[key] = learner
    return learner


for _learner in (
    CEMLearner,
    TamerLearner,
    QLearningLearner,
    PolicyGradientLearner,
    TetrisDQN,
    SarsaKeepers,
    KeepawayDQN,
    GymDQN,
    GymTamer,
    GymPPO,
):
    register_learner(_learner)
register_domain(
    Domain("tetris", check_tetris_domain, check_tetris_evaluation, evaluate_tetris, format_summary, "cem")
)
register_domain(
    Domain(
        "keepaway",
        check_keepaway_domain,
        check_keepaway_evaluation,
        evaluate_keepaway,
        format_keepaway_summary,
        "sarsa",
        spread=True,
    )
)
register_domain(  # any Gymnasium task or TorchRL env (domain.env_id, domain.make)
    Domain(
        "gym", check_gym_domain, check_gym_evaluation, evaluate_gym, format_gym_summary, "dqn", spread=True
    )
)


def domain_for(cfg: DictConfig) -> Domain:
    """The registered domain ``domain.name`` names (``ConfigError`` naming the allowed ones otherwise)."""
    return DOMAINS[require_choice(cfg, "domain.name", DOMAINS)]


def agent_names() -> list[str]:
    """Every agent that learns some domain."""
    return sorted({agent for _, agent in LEARNERS})


def learners() -> list[type[Learner]]:
    """Every registered learner class."""
    return list(LEARNERS.values())


def learner_for(agent: str, domain: str = "tetris") -> type[Learner]:
    """The learner class of ``agent`` on ``domain``; ``ConfigError`` naming what is allowed otherwise."""
    if (domain, agent) in LEARNERS:
        return LEARNERS[domain, agent]
    here = sorted(a for d, a in LEARNERS if d == domain)
    there = sorted(d for d, a in LEARNERS if a == agent)
    default = DOMAINS[domain].default_agent if domain in DOMAINS else (here[0] if here else agent)
    learns = f"agent={agent} learns {', '.join(there)}; " if there else f"agent={agent} learns no domain; "
    raise ConfigError(
        f"domain={domain} agent={agent} is invalid: {learns}domain={domain} is learned by "
        f"{', '.join(f'agent={a}' for a in here) or 'no agent'} (e.g. domain={domain} agent={default})"
    )


def evidence_givers() -> dict[str, list[str]]:
    """For each kind of learner evidence a fusion weight may need, the agents whose learners give it."""
    givers: dict[str, list[str]] = {}
    for learner in learners():
        for evidence in sorted(learner.weight_evidence):
            givers.setdefault(evidence, [])
            if learner.agent not in givers[evidence]:
                givers[evidence].append(learner.agent)
    return givers
