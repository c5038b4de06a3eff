"""Trainers that give feedback to a learning agent: simulated ones (oracle, value proxy, human-like timing),
a replay of a recorded log, and the queue that a live trainer's thread fills.

The simulated trainers are programs standing in for a person in experiments and tests; they are never
presented as people.
"""

from hfrl_torch.trainers.base import Events, Trainer, board_of, board_session
from hfrl_torch.trainers.oracle import OracleTrainer
from hfrl_torch.trainers.queue_trainer import QueueTrainer
from hfrl_torch.trainers.reference_policy import ReferenceEvaluation, evaluate_placements
from hfrl_torch.trainers.replay import ReplayTrainer
from hfrl_torch.trainers.timing import HumanLikeTiming, sample_delays, sample_gamma
from hfrl_torch.trainers.value_proxy import ValueProxyTrainer

__all__ = [
    "Events",
    "HumanLikeTiming",
    "OracleTrainer",
    "QueueTrainer",
    "ReferenceEvaluation",
    "ReplayTrainer",
    "Trainer",
    "ValueProxyTrainer",
    "board_of",
    "board_session",
    "evaluate_placements",
    "sample_delays",
    "sample_gamma",
]
