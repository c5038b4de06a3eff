"""Keepaway as one SMDP per field for a DQN: a step is one decision of the team's keeper with the ball.

With ``KeepawayEnv(sync="all")`` every step runs each field to its next decision, whichever keeper makes it,
so the time the ball stayed in play during the step is ``keys.STEP_CYCLES``. :class:`TeamSteps` makes that the
reward, in seconds: a team's returns add up to the episode's hold time after its first decision, and one Q
network, reading the deciding keeper's own state variables, serves every keeper (the reference's shared
"hive mind" weights, as one SMDP).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.envs.transforms import Transform

from hfrl_torch import keys

__all__ = ["CYCLES_PER_SECOND", "TeamSteps"]

CYCLES_PER_SECOND = 10.0


class TeamSteps(Transform):
    """``reward <- STEP_CYCLES / 10``: each field's step lasted that many simulated seconds."""

    def __init__(self) -> None:
        super().__init__(in_keys=[keys.STEP_CYCLES], out_keys=[keys.REWARD])

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        cycles = next_tensordict.get(keys.STEP_CYCLES)
        reward = next_tensordict.get(keys.REWARD)
        seconds = (cycles.to(torch.float32) / CYCLES_PER_SECOND).reshape(reward.shape)
        next_tensordict.set(keys.REWARD, seconds.to(reward.dtype))
        return next_tensordict
