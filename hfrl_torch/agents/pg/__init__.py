"""Policy gradient over a softmax of afterstate values: REINFORCE with a baseline and the natural gradient."""

from hfrl_torch.agents.pg.pg import PolicyGradient, natural_direction, score_and_fisher

__all__ = ["PolicyGradient", "natural_direction", "score_and_fisher"]
