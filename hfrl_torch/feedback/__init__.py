"""Human feedback: events and their queue, the feedback log, credit assignment and the trust factor."""

from hfrl_torch.feedback.credit import (
    CreditModel,
    DelayDensity,
    GammaDelay,
    PreviousStep,
    UniformDelay,
    credit_weights,
)
from hfrl_torch.feedback.events import (
    MAX_ABS_FEEDBACK,
    FeedbackEvent,
    FeedbackQueue,
    FeedbackQueueClosedError,
    FeedbackQueueFullError,
)
from hfrl_torch.feedback.log import (
    DuplicateFeedbackWarning,
    FeedbackLog,
    FeedbackLogContents,
    FeedbackLogError,
    load_feedback_log,
    read_feedback_log,
)
from hfrl_torch.feedback.trust import IncrementalTrust, MatchRate, trust_from_policies

__all__ = [
    "MAX_ABS_FEEDBACK",
    "CreditModel",
    "DelayDensity",
    "DuplicateFeedbackWarning",
    "FeedbackEvent",
    "FeedbackLog",
    "FeedbackLogContents",
    "FeedbackLogError",
    "FeedbackQueue",
    "FeedbackQueueClosedError",
    "FeedbackQueueFullError",
    "GammaDelay",
    "IncrementalTrust",
    "MatchRate",
    "PreviousStep",
    "UniformDelay",
    "credit_weights",
    "load_feedback_log",
    "read_feedback_log",
    "trust_from_policies",
]
