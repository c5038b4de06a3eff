"""Errors that reach the user as one clear line (what was wrong, what is allowed)."""

from __future__ import annotations


class UserError(Exception):
    """Bad input from the user: printed as ``error: <message>`` and exit status 2, no traceback."""


class ConfigError(UserError):
    """A config value outside what is allowed."""


class CheckpointError(UserError):
    """A checkpoint that is missing, corrupt, or made for another domain or agent."""
