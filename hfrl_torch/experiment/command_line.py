"""What the command line of the Hydra app running now set: its task overrides."""

from __future__ import annotations

from hydra.core.hydra_config import HydraConfig


def task_overrides() -> list[str]:
    """The overrides of this job's command line (``domain.width=8``, ...); none outside a Hydra app."""
    try:
        return list(HydraConfig.get().overrides.task)
    except ValueError:  # called outside a Hydra app (tests)
        return []
