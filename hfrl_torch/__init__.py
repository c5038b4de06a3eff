"""hfrl_torch: agents that learn from a person's feedback and the environment's reward at once."""

from hfrl_torch.envs.registration import register_envs

__version__ = "0.1.0"

register_envs()
