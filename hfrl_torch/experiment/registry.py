"""Which learner each ``agent`` is: the registry ``train.py`` dispatches through."""

from __future__ import annotations

from hfrl_torch.experiment.learners.keepaway_sarsa import SarsaKeepers
from hfrl_torch.experiment.learners.tetris_cem import CEMLearner
from hfrl_torch.experiment.learners.tetris_pg import PolicyGradientLearner
from hfrl_torch.experiment.learners.tetris_qlearning import QLearningLearner
from hfrl_torch.experiment.learners.tetris_tamer import TamerLearner
from hfrl_torch.experiment.run import Learner

LEARNERS: dict[str, type[Learner]] = {
    learner.agent: learner
    for learner in (CEMLearner, TamerLearner, QLearningLearner, PolicyGradientLearner, SarsaKeepers)
}


def learner_for(agent: str) -> type[Learner]:
    """The learner class of ``agent`` (``cem``, ``tamer``, ``qlearning``, ``pg``, ``sarsa``)."""
    if agent not in LEARNERS:
        raise KeyError(f"agent={agent!r} has no learner; allowed: {', '.join(LEARNERS)}")
    return LEARNERS[agent]
