"""A scripted reference policy for Acrobot-v1: ``trainer.reference=examples.acrobot:reference``.

Torque the second joint in the direction it already turns (standing still: +1), which pumps energy into the
swing until the tip rises above the bar: 65-211 steps (mean 85) over 100 seeded episodes, every one ending
at the bar well before the 500-step limit
(``python evaluate.py domain=gym domain.env_id=Acrobot-v1 policy=examples.acrobot:reference``).
"""

from __future__ import annotations

import torch


def reference(obs: torch.Tensor) -> torch.Tensor:
    """Actions [B] (0 torque -1, 1 none, 2 torque +1) for observations [B, 6] (cos and sin of both angles,
    then both angular velocities)."""
    return torch.where(obs[..., 5] >= 0, 2, 0).to(torch.int64)
