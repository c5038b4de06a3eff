"""Shared core: errors, config checks, checkpoints, statistics and logging."""
