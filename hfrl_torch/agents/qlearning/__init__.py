"""Q-learning with a linear Q over afterstate features (Watkins 1989; the thesis's Algorithm 4)."""

from hfrl_torch.agents.qlearning.qlearning import LinearQLearning, allowed_placements

__all__ = ["LinearQLearning", "allowed_placements"]
