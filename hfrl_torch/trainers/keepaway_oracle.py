"""A SIMULATED keepaway trainer (Griffith et al.'s oracle), watching a batch of fields at once.

At each decision of a field's keeper, with probability L (``frequency``) the oracle gives +1 if the keeper's
action is the reference policy's in that state (the spec's hand-coded benchmark, or a trained checkpoint's
greedy choice) and -1 otherwise, flipped with probability 1 - C (``consistency``); it arrives after a
reaction delay drawn from a density (the thesis's gamma(2.0, 0.28) by default). One event per field and
decision at most; times are each field's simulated clock (seconds). Every event is appended to the feedback
log, labelled with its field.

The human-like options of ``trainers.timing`` apply per field: fatigue (an event is kept with probability
exp(-t / tau), t the field's simulated seconds), positive bias (a -1 becomes silence with that
probability) and absence (away for a whole episode with that probability, drawn at each episode start).
"""

from __future__ import annotations

from collections.abc import Callable
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
    """Judges keepers' decisions against a reference policy (source ``simulated:keepaway_oracle``).

    :param keepers: n, and ``takers``: m, of the task (the state variables' layout).
    :param frequency: L, the probability of judging a decision.
    :param consistency: C, the probability that the judgement is the oracle's (else flipped).
    :param delay: reaction-delay density (or fixed seconds > 0).
    :param seed: seed of its generator (five draws per field and decision, whatever happens).
    :param log: feedback log every event is appended to.
    :param reference: the policy judged against, ``(obs [B, F], keeper [B]) -> actions [B]`` (None: the
        hand-coded policy).
    :param fatigue_tau: seconds over which the frequency falls by a factor e (None: no fatigue).
    :param positive_bias: probability that a -1 becomes silence.
    :param absence: probability, per field and episode, that the trainer is away for the episode.
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
        reference: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
        fatigue_tau: float | None = None,
        positive_bias: float = 0.0,
        absence: float = 0.0,
    ) -> None:
        for name, v in (
            ("frequency", frequency),
            ("consistency", consistency),
            ("positive_bias", positive_bias),
            ("absence", absence),
        ):
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"KeepawayOracle {name} must be within [0, 1], got {v!r}")
        if fatigue_tau is not None and not fatigue_tau > 0:
            raise ValueError(f"KeepawayOracle fatigue_tau must be None or > 0 seconds, got {fatigue_tau!r}")
        self.keepers, self.takers = keepers, takers
        self.frequency, self.consistency = float(frequency), float(consistency)
        self.delay = GammaDelay(2.0, 0.28) if delay is None else delay
        self.generator = torch.Generator().manual_seed(seed)
        self.log = log
        self.reference = reference
        self.fatigue_tau, self.positive_bias, self.absence = fatigue_tau, float(positive_bias), float(absence)
        self.present: torch.Tensor | None = None  # per field, drawn by new_episodes
        self.given = 0

    def new_episodes(self, starting: torch.Tensor) -> None:
        """Draw, for the fields flagged in ``starting`` [B], whether the trainer watches their new episode."""
        b = starting.shape[0]
        away = torch.rand(b, generator=self.generator, dtype=torch.float64) < self.absence
        if self.present is None or self.present.shape[0] != b:
            self.present = torch.ones(b, dtype=torch.bool)
        self.present = torch.where(starting.cpu().to(torch.bool), ~away, self.present)

    def give(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        deciding: torch.Tensor,
        time: torch.Tensor,
        keeper: torch.Tensor | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Feedback on the decisions ``action`` [B] taken in states ``obs`` [B, F] by ``keeper`` [B] where
        ``deciding`` [B], at simulated times ``time`` [B]: values [B] (0 = none) and the times they arrive."""
        b = action.shape[0]
        speaks, flips = oracle_noise(b, self.frequency, self.consistency, self.generator)
        delays = sample_delays(self.delay, b, self.generator)
        keep = torch.rand(b, generator=self.generator, dtype=torch.float64)
        unbias = torch.rand(b, generator=self.generator, dtype=torch.float64)
        obs, time = obs.cpu(), time.cpu().to(torch.float64)
        keeper = torch.zeros(b, dtype=torch.int64) if keeper is None else keeper.cpu()
        if self.reference is None:
            wanted = hand_coded_actions(obs, self.keepers, self.takers)
        else:
            wanted = self.reference(obs, keeper).cpu()
        judged = torch.where(action.cpu() == wanted, 1.0, -1.0) * torch.where(flips, -1.0, 1.0)
        give = speaks & deciding.cpu().to(torch.bool)
        if self.present is not None:
            give &= self.present
        if self.fatigue_tau is not None:
            give &= keep < torch.exp(-time / self.fatigue_tau)
        give &= ~((judged < 0) & (unbias < self.positive_bias))
        values = torch.where(give, judged, 0.0).to(torch.float64)
        times = time + delays
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
        return {"given": self.given, "generator": self.generator.get_state(), "present": self.present}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        try:
            self.given = int(state["given"])
            self.generator.set_state(state["generator"])
            present = state.get("present")
            self.present = None if present is None else present.to(torch.bool).clone()
        except (KeyError, TypeError, RuntimeError, AttributeError) as e:
            raise CheckpointError(f"bad KeepawayOracle state in the checkpoint ({e!r})") from None
