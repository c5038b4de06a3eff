"""Human-like timing around a simulated trainer: delays, fatigue, positive bias, absences, tailing off.

Still a simulated trainer, not a person. It wraps another trainer (the oracle or the value proxy) and
changes when, whether and how its events arrive, the way people's feedback is reported to behave
(Knox & Stone 2009 for delays; Knox et al. 2012 and Loftin et al. 2014 for fading, biased feedback):

- reaction delay: each event's time is the placement's time plus a delay drawn from a density
  (gamma(2, 0.28 s) by default: mean 0.56 s, as in the thesis);
- fatigue: an event is kept with probability exp(-t / tau), t the seconds since the first step, so the
  frequency falls as L_t = L0 exp(-t / tau);
- positive bias: a negative event becomes silence (or +1) with probability ``positive_bias``;
- absence: with probability ``absence`` per game and board, the trainer gives nothing for that game;
- tailing off: an event is kept with probability ``tail_lines / (tail_lines + m)``, m the mean lines of
  that board's last ``tail_games`` games, so feedback thins out as the agent improves.

All draws come from one seeded ``torch.Generator`` in a fixed order per step, so a run is a function of
its seed and of the wrapped trainer's.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import replace
from typing import Any

import numpy as np
import torch
from tensordict import TensorDictBase

from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.feedback.credit import DelayDensity, GammaDelay, UniformDelay
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.base import Events, Trainer, all_active

BIAS_TARGETS = ("silence", "positive")


def sample_gamma(shape: float, scale: float, n: int, generator: torch.Generator) -> torch.Tensor:
    """``n`` gamma(shape, scale) draws (float64) from ``generator`` (Marsaglia & Tsang 2000). The normal
    and uniform draws come from ``generator``; the acceptance test runs in numpy, a few microseconds for
    the ten-odd draws of a step where torch's per-op cost is several times that."""
    boost = shape < 1.0
    k = shape + 1.0 if boost else shape
    d = k - 1.0 / 3.0
    c = 1.0 / math.sqrt(9.0 * d)
    out = np.empty(n, dtype=np.float64)
    todo = np.arange(n)
    while todo.size > 0:
        m = todo.size
        x = torch.randn(m, generator=generator, dtype=torch.float64).numpy()
        u = torch.rand(m, generator=generator, dtype=torch.float64).numpy()
        t = 1.0 + c * x
        v = t * t * t  # torch's (1 + c x) ** 3 is this product, so the draws are torch's to the bit
        with np.errstate(divide="ignore"):
            ok = (v > 0) & (np.log(u) < 0.5 * x * x + d - d * v + d * np.log(np.maximum(v, 1e-300)))
        out[todo[ok]] = d * v[ok]
        todo = todo[~ok]
    draws = torch.from_numpy(out)
    if boost:
        draws = draws * torch.rand(n, generator=generator, dtype=torch.float64) ** (1.0 / shape)
    return draws * scale


def sample_delays(delay: DelayDensity | float, n: int, generator: torch.Generator) -> torch.Tensor:
    """``n`` reaction delays in seconds: from a ``GammaDelay`` / ``UniformDelay`` density, or a constant."""
    if isinstance(delay, GammaDelay):
        return sample_gamma(delay.shape, delay.scale, n, generator)
    if isinstance(delay, UniformDelay):
        return delay.a + (delay.b - delay.a) * torch.rand(n, generator=generator, dtype=torch.float64)
    if isinstance(delay, (int, float)) and not isinstance(delay, bool):
        return torch.full((n,), float(delay), dtype=torch.float64)
    raise TypeError(f"delay must be a GammaDelay, a UniformDelay or seconds > 0, got {delay!r}")


class HumanLikeTiming(Trainer):
    """Wraps a simulated trainer with human-like timing (see the module docstring); keeps its source.

    :param trainer: the wrapped trainer (give it no log; pass the log here).
    :param delay: reaction-delay density (``GammaDelay``, ``UniformDelay``) or fixed seconds > 0.
    :param fatigue_tau: seconds over which the frequency falls by a factor e (None = no fatigue).
    :param positive_bias: probability that a negative event becomes ``bias_to``.
    :param bias_to: ``"silence"`` (dropped) or ``"positive"`` (its sign flipped).
    :param absence: probability, per game and board, that the trainer is away for the whole game.
    :param tail_lines: lines per game at which the frequency is halved (None = no tailing off).
    :param tail_games: how many recent games of a board the tailing off averages.
    :param seed: seed of the generator.
    :param log: feedback log every event is appended to.
    """

    def __init__(
        self,
        trainer: Trainer,
        delay: DelayDensity | float | None = None,
        fatigue_tau: float | None = None,
        positive_bias: float = 0.0,
        bias_to: str = "silence",
        absence: float = 0.0,
        tail_lines: float | None = None,
        tail_games: int = 3,
        seed: int = 0,
        log: FeedbackLog | None = None,
    ) -> None:
        super().__init__(log)
        delay = GammaDelay(2.0, 0.28) if delay is None else delay
        if isinstance(delay, (int, float)) and not delay > 0:
            raise ValueError(f"HumanLikeTiming delay must be > 0 seconds, got {delay!r}")
        if fatigue_tau is not None and not fatigue_tau > 0:
            raise ValueError(f"HumanLikeTiming fatigue_tau must be None or > 0 seconds, got {fatigue_tau!r}")
        for name, p in (("positive_bias", positive_bias), ("absence", absence)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"HumanLikeTiming {name} must be within [0, 1], got {p!r}")
        if bias_to not in BIAS_TARGETS:
            raise ValueError(
                f"HumanLikeTiming bias_to={bias_to!r} is invalid; allowed: {', '.join(BIAS_TARGETS)}"
            )
        if tail_lines is not None and not tail_lines > 0:
            raise ValueError(f"HumanLikeTiming tail_lines must be None or > 0, got {tail_lines!r}")
        if tail_games < 1:
            raise ValueError(f"HumanLikeTiming tail_games must be >= 1, got {tail_games!r}")
        self.trainer = trainer
        self.source = trainer.source
        self.delay = delay
        self.fatigue_tau = fatigue_tau
        self.positive_bias = float(positive_bias)
        self.bias_to = bias_to
        self.absence = float(absence)
        self.tail_lines = tail_lines
        self.tail_games = tail_games
        self.generator = torch.Generator().manual_seed(seed)
        self.start: float | None = None
        self.absent: torch.Tensor | None = None
        self.episode: torch.Tensor | None = None
        self.recent: list[deque[float]] = []

    def keep_probability(self, time: float, boards: int) -> torch.Tensor:
        """Probability [B] that an event survives fatigue and tailing off at ``time``."""
        p = torch.ones(boards, dtype=torch.float64)
        if self.fatigue_tau is not None:
            p = p * math.exp(-(time - (self.start if self.start is not None else time)) / self.fatigue_tau)
        if self.tail_lines is not None:
            m = torch.tensor([sum(r) / len(r) if r else 0.0 for r in self.recent], dtype=torch.float64)
            p = p * self.tail_lines / (self.tail_lines + m)
        return p

    def _track_episodes(self, episode: torch.Tensor) -> None:
        b = episode.shape[0]
        u = torch.rand(b, generator=self.generator, dtype=torch.float64)
        ep = episode.reshape(b).to(torch.int64).cpu()
        new = torch.ones(b, dtype=torch.bool) if self.episode is None else ep != self.episode
        drawn = u < self.absence
        self.absent = drawn if self.absent is None else torch.where(new, drawn, self.absent)
        self.episode = ep.clone()

    def give(
        self,
        obs: TensorDictBase,
        action: torch.Tensor,
        time: float,
        episode: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> Events:
        act = all_active(obs, active)
        b = act.shape[0]
        if self.start is None:
            self.start = time
            self.recent = [deque(maxlen=self.tail_games) for _ in range(b)]
        self._track_episodes(episode)
        base = self.trainer.give(obs, action, time, episode, act)
        m = max(1, *(len(e) for e in base))
        keep_u = torch.rand(b, m, generator=self.generator, dtype=torch.float64)
        bias_u = torch.rand(b, m, generator=self.generator, dtype=torch.float64)
        delays = sample_delays(self.delay, b * m, self.generator).view(b, m)
        keep_p = self.keep_probability(time, b)
        assert self.absent is not None
        absent, keep_u, keep_p = self.absent.tolist(), keep_u.tolist(), keep_p.tolist()
        bias_u, delays = bias_u.tolist(), delays.tolist()
        events: Events = []
        for i, evs in enumerate(base):
            out = []
            for j, ev in enumerate(evs):
                if absent[i] or keep_u[i][j] >= keep_p[i]:
                    continue
                value = ev.value
                if value < 0 and bias_u[i][j] < self.positive_bias:
                    if self.bias_to == "silence":
                        continue
                    value = -value
                out.append(replace(ev, time=time + delays[i][j], value=value))
            events.append(out)
        return self._emit(events)

    def state_dict(self) -> dict[str, Any]:
        """The base state plus the session start, the absences, the games seen and the recent lines."""
        return {
            **super().state_dict(),
            "start": self.start,
            "absent": None if self.absent is None else self.absent.clone(),
            "episode": None if self.episode is None else self.episode.clone(),
            "recent": [list(r) for r in self.recent],
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        super().load_state_dict(state)
        try:
            self.start = None if state["start"] is None else float(state["start"])
            self.absent = (
                None if state["absent"] is None else torch.as_tensor(state["absent"], dtype=torch.bool)
            )
            self.episode = (
                None if state["episode"] is None else torch.as_tensor(state["episode"], dtype=torch.int64)
            )
            self.recent = [deque((float(x) for x in r), maxlen=self.tail_games) for r in state["recent"]]
        except (KeyError, TypeError, ValueError) as e:
            raise CheckpointError(f"bad HumanLikeTiming state in the checkpoint ({e!r})") from None

    def end_games(self, done: torch.Tensor, lines: torch.Tensor) -> None:
        for i in torch.nonzero(done.reshape(-1).cpu()).flatten().tolist():
            if i < len(self.recent):
                self.recent[i].append(float(lines.reshape(-1)[i]))
        self.trainer.end_games(done, lines)
