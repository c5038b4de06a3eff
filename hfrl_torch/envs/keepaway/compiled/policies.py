"""policies.py in compiled code: the benchmark keepers deciding inside the compiled loop."""

from __future__ import annotations

import numpy as np

from hfrl_torch.envs.keepaway.compiled.common import _F, M, N, _next
from hfrl_torch.envs.keepaway.policies import HAND_DIST_WEIGHT, HAND_HOLD_SCORE, HAND_SAFE_DISTANCE

HOLD, RANDOM, HAND = 0, 1, 2
POLICY_CODES = {"hold": HOLD, "random": RANDOM, "hand": HAND}


@_F
def _policy_action(policy, obs, rng, b, ip):
    """The benchmark keepers (policies.py): ``policy`` HOLD (Always Hold), RANDOM (Random, drawn from
    the field's stream) or HAND (Hand-coded) on the deciding keeper's state variables ``obs``."""
    n, m = ip[N], ip[M]
    if policy == HOLD:
        return 0
    if policy == RANDOM:
        return min(np.int64(_next(rng, b) * n), n - 1)
    if obs[n] > HAND_SAFE_DISTANCE:
        return 0
    start = 2 * n + 2 * m - 1
    best, action = np.float32(HAND_HOLD_SCORE), 0
    for k in range(n - 1):
        weighted = np.float32(HAND_DIST_WEIGHT) * np.float32(obs[start + k])
        score = np.float32(weighted + np.float32(obs[start + n - 1 + k]))
        if score > best:
            best, action = score, k + 1
    return action
