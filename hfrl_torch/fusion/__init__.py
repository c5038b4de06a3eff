"""Fusion: combining the person's reward model H^ with the environment (thesis eqs. 4.1-4.4, 5.1; TAMER+RL).

One component, :class:`Fusion`, applies every scheme of :mod:`hfrl_torch.fusion.schemes` at the decision
(which action is taken) and at the reward (what the learner is trained on), counts the matches behind the
trust factor and updates the weights (:mod:`hfrl_torch.fusion.schedules`, :mod:`hfrl_torch.fusion.trust`).
Its TorchRL faces are :class:`FeedbackFusion` (a transform on the env) and :class:`FusionModule` (a module
in the policy); :mod:`hfrl_torch.fusion.compiled` is its compiled twin for whole Tetris games.
"""

from hfrl_torch.fusion.fusion import SCALINGS, Fusion, choosable
from hfrl_torch.fusion.schedules import (
    AnnealedWeight,
    ConstantWeight,
    TrustWeight,
    WeightSchedule,
    as_schedule,
)
from hfrl_torch.fusion.schemes import (
    DECISION_SCHEMES,
    FUSIONS,
    OPTIONS,
    REWARD_SCHEMES,
    SCHEMES,
    Scheme,
    fuse_values,
    rescale_range,
    signed_power,
)
from hfrl_torch.fusion.transform import HUMAN_REWARD_ESTIMATE, FeedbackFusion, FusionModule
from hfrl_torch.fusion.trust import IncrementalTrust, MatchCounter, trust_from_policies

__all__ = [
    "DECISION_SCHEMES",
    "FUSIONS",
    "HUMAN_REWARD_ESTIMATE",
    "OPTIONS",
    "REWARD_SCHEMES",
    "SCALINGS",
    "SCHEMES",
    "AnnealedWeight",
    "ConstantWeight",
    "FeedbackFusion",
    "Fusion",
    "FusionModule",
    "IncrementalTrust",
    "MatchCounter",
    "Scheme",
    "TrustWeight",
    "WeightSchedule",
    "as_schedule",
    "choosable",
    "fuse_values",
    "rescale_range",
    "signed_power",
    "trust_from_policies",
]
