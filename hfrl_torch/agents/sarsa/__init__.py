"""SMDP Sarsa(lambda) with hashed tile coding (Stone, Sutton & Kuhlmann 2005; thesis Figure 5.4)."""

from hfrl_torch.agents.sarsa.keepers import LEARNER_KERNELS, resolve_learner_kernels, sarsa_keepers
from hfrl_torch.agents.sarsa.sarsa import MAX_TRACES, SarsaLambda, trace_capacity
from hfrl_torch.agents.sarsa.sarsa_numba import SarsaLambdaNumba

__all__ = [
    "LEARNER_KERNELS",
    "MAX_TRACES",
    "SarsaLambda",
    "SarsaLambdaNumba",
    "resolve_learner_kernels",
    "sarsa_keepers",
    "trace_capacity",
]
