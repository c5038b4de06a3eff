"""Which learner each ``agent`` is: the registry ``train.py`` dispatches through."""

from __future__ import annotations

from hfrl_torch.experiment.learners.keepaway_dqn import KeepawayDQN
from hfrl_torch.experiment.learners.keepaway_sarsa import SarsaKeepers
from hfrl_torch.experiment.learners.tetris_cem import CEMLearner
from hfrl_torch.experiment.learners.tetris_dqn import TetrisDQN
from hfrl_torch.experiment.learners.tetris_pg import PolicyGradientLearner
from hfrl_torch.experiment.learners.tetris_qlearning import QLearningLearner
from hfrl_torch.experiment.learners.tetris_tamer import TamerLearner
from hfrl_torch.experiment.run import Learner

LEARNERS: dict[str, type[Learner]] = {
    learner.agent: learner
    for learner in (CEMLearner, TamerLearner, QLearningLearner, PolicyGradientLearner, SarsaKeepers)
}


# agents that learn either domain: one learner class per domain
DOMAIN_LEARNERS: dict[tuple[str, str], type[Learner]] = {
    (learner.domain, learner.agent): learner for learner in (TetrisDQN, KeepawayDQN)
}


def learner_for(agent: str, domain: str = "tetris") -> type[Learner]:
    """The learner class of ``agent`` (``cem``, ``tamer``, ``qlearning``, ``pg``, ``sarsa``; ``dqn`` in
    ``domain``)."""
    if (domain, agent) in DOMAIN_LEARNERS:
        return DOMAIN_LEARNERS[domain, agent]
    if agent not in LEARNERS:
        allowed = sorted({*LEARNERS, *(a for _, a in DOMAIN_LEARNERS)})
        raise KeyError(f"agent={agent!r} has no learner; allowed: {', '.join(allowed)}")
    return LEARNERS[agent]


def learners() -> list[type[Learner]]:
    """Every learner class, each once."""
    return [*LEARNERS.values(), *DOMAIN_LEARNERS.values()]
