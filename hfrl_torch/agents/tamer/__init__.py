"""TAMER: learning a model of the trainer's reward and acting greedily on it (Knox & Stone 2009)."""

from hfrl_torch.agents.tamer.primitive_tamer import PrimitiveTamerAgent
from hfrl_torch.agents.tamer.tamer import TamerAgent, placement_deltas

__all__ = ["PrimitiveTamerAgent", "TamerAgent", "placement_deltas"]
