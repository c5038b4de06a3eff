"""Human feedback: events and their queue, the channel into the tensordict, the feedback log and credit."""

from hfrl_torch.feedback.channel import FeedbackChannel
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

__all__ = [
    "MAX_ABS_FEEDBACK",
    "CreditModel",
    "DelayDensity",
    "DuplicateFeedbackWarning",
    "FeedbackChannel",
    "FeedbackEvent",
    "FeedbackLog",
    "FeedbackLogContents",
    "FeedbackLogError",
    "FeedbackQueue",
    "FeedbackQueueClosedError",
    "FeedbackQueueFullError",
    "GammaDelay",
    "PreviousStep",
    "UniformDelay",
    "credit_weights",
    "load_feedback_log",
    "read_feedback_log",
]
