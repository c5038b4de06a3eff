"""Deep Q-learning on TorchRL's own parts (``DQNLoss``, replay buffer, soft target), with H^ fused."""

from hfrl_torch.agents.dqn.dqn import CHOOSABLE, DeepQ, choosable_module
from hfrl_torch.agents.dqn.human import (
    ChosenEstimate,
    HumanValues,
    HumanValuesModule,
    SharedLinearTamer,
    SharedTileTamer,
)
from hfrl_torch.agents.dqn.team_steps import TeamSteps

__all__ = [
    "CHOOSABLE",
    "ChosenEstimate",
    "DeepQ",
    "HumanValues",
    "HumanValuesModule",
    "SharedLinearTamer",
    "SharedTileTamer",
    "TeamSteps",
    "choosable_module",
]
