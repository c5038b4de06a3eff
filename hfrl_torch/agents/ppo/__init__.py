"""PPO on TorchRL's own parts (``ClipPPOLoss``, ``GAE``), with H^ fused into its policy's preferences."""

from hfrl_torch.agents.ppo.ppo import PLAYED_WEIGHT, PPO, PlayedWeight

__all__ = ["PLAYED_WEIGHT", "PPO", "PlayedWeight"]
