"""The browser trainer: a person teaches the agent live from a web page (``trainer=interactive``)."""

from hfrl_torch.interactive.messages import MessageError, parse_message
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession

__all__ = ["MessageError", "TeachingServer", "TeachingSession", "parse_message"]
