"""Fusion: combining the person's reward model H^ with the environment (thesis eqs. 4.1-4.4, 5.1; TAMER+RL).

Decision level (:class:`FusedActionSelector`, :func:`fuse_values`): which action is taken. Reward level
(:class:`FeedbackFusion`): which reward the learner is trained on. Weights over episodes come from
:mod:`hfrl_torch.fusion.schedules`. :data:`SCHEMES` lists every scheme with the levels it acts at.
"""

from hfrl_torch.fusion.schedules import (
    AnnealedWeight,
    ConstantWeight,
    TrustWeight,
    WeightSchedule,
    as_schedule,
)
from hfrl_torch.fusion.schemes import (
    DECISION_SCHEMES,
    REWARD_SCHEMES,
    SCHEMES,
    TARGET_SCHEMES,
    FusedActionSelector,
    Scheme,
    fuse_values,
    signed_power,
)
from hfrl_torch.fusion.transform import HUMAN_REWARD_ESTIMATE, FeedbackFusion

__all__ = [
    "DECISION_SCHEMES",
    "HUMAN_REWARD_ESTIMATE",
    "REWARD_SCHEMES",
    "SCHEMES",
    "TARGET_SCHEMES",
    "AnnealedWeight",
    "ConstantWeight",
    "FeedbackFusion",
    "FusedActionSelector",
    "Scheme",
    "TrustWeight",
    "WeightSchedule",
    "as_schedule",
    "fuse_values",
    "signed_power",
]
