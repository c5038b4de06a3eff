"""SMDP Sarsa(lambda) with hashed tile coding (Stone, Sutton & Kuhlmann 2005; thesis Figure 5.4)."""

from hfrl_torch.agents.sarsa.keepers import sarsa_keepers
from hfrl_torch.agents.sarsa.sarsa import MAX_TRACES, SarsaLambda, trace_capacity

__all__ = ["MAX_TRACES", "SarsaLambda", "sarsa_keepers", "trace_capacity"]
