"""A SIMULATED keepaway trainer (Griffith et al.'s oracle), watching a batch of fields at once.

At each decision of a field's keeper, with probability L (``frequency``) the oracle gives +1 if the keeper's
action is the hand-coded policy's in that state (the spec's benchmark) and -1 otherwise, flipped with
probability 1 - C (``consistency``); it arrives after a reaction delay drawn from a density (the thesis's
gamma(2.0, 0.28) by default). One event per field and decision at most; times are each field's simulated
clock (seconds). Every event is appended to the feedback log, labelled with its field.
"""

from __future__ import annotations

from typing import Any

import torch

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.envs.keepaway.policies import hand_coded_actions
from hfrl_torch.feedback.credit import DelayDensity, GammaDelay
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.base import board_session
from hfrl_torch.trainers.oracle import oracle_noise
from hfrl_torch.trainers.timing import sample_delays

SOURCE = "simulated:keepaway_oracle"


class KeepawayOracle:
    """Judges keepers' decisions against the hand-coded policy (source ``simulated:keepaway_oracle``).

    :param keepers: n, and ``takers``: m, of the task (the state variables' layout).
    :param frequency: L, the probability of judging a decision.
    :param consistency: C, the probability that the judgement is the oracle's (else flipped).
    :param delay: reaction-delay density (or fixed seconds > 0).
    :param seed: seed of its generator (three draws per field and decision, whatever happens).
    :param log: feedback log every event is appended to.
    """

    source = SOURCE

    def __init__(
        self,
        keepers: int,
        takers: int,
        frequency: float = 0.5,
        consistency: float = 0.9,
        delay: DelayDensity | float | None = None,
        seed: int = 0,
        log: FeedbackLog | None = None,
    ) -> None:
        for name, v in (("frequency", frequency), ("consistency", consistency)):
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"KeepawayOracle {name} must be within [0, 1], got {v!r}")
        self.keepers, self.takers = keepers, takers
        self.frequency, self.consistency = float(frequency), float(consistency)
        self.delay = GammaDelay(2.0, 0.28) if delay is None else delay
        self.generator = torch.Generator().manual_seed(seed)
        self.log = log
        self.given = 0

    def give(
        self, obs: torch.Tensor, action: torch.Tensor, deciding: torch.Tensor, time: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Feedback on the decisions ``action`` [B] taken in states ``obs`` [B, F] where ``deciding`` [B]
        at simulated times ``time`` [B]: values [B] (0 = none) and the times they arrive [B]."""
        b = action.shape[0]
        speaks, flips = oracle_noise(b, self.frequency, self.consistency, self.generator)
        delays = sample_delays(self.delay, b, self.generator)
        right = action.cpu() == hand_coded_actions(obs.cpu(), self.keepers, self.takers)
        judged = torch.where(right, 1.0, -1.0) * torch.where(flips, -1.0, 1.0)
        give = speaks & deciding.cpu().to(torch.bool)
        values = torch.where(give, judged, 0.0).to(torch.float64)
        times = time.cpu().to(torch.float64) + delays
        self.given += int(give.sum())
        if self.log is not None and bool(give.any()):
            session = self.log.session
            self.log.extend(
                FeedbackEvent(
                    time=float(times[i]),
                    value=float(values[i]),
                    source=SOURCE,
                    session=board_session(session, i, b),
                )
                for i in give.nonzero().flatten().tolist()
            )
        return values, times

    def state_dict(self) -> dict[str, Any]:
        """The generator's state and the count, for a resumed run."""
        return {"given": self.given, "generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        try:
            self.given = int(state["given"])
            self.generator.set_state(state["generator"])
        except (KeyError, TypeError, RuntimeError) as e:
            raise CheckpointError(f"bad KeepawayOracle state in the checkpoint ({e!r})") from None
