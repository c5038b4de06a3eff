"""Oracle trainer with frequency L and consistency C (Griffith et al., "Policy Shaping", NIPS 2013).

A simulated trainer, not a person: at each placement it gives feedback with probability L; the
feedback is +1 when the agent's placement is the reference policy's, -1 otherwise, flipped with
probability 1 - C. The reference policy for Tetris is Dellacherie's hand weights over the Dellacherie
features of the afterstates (``reference_policy``).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from hfrl_torch.envs.tetris.features import DELLACHERIE_WEIGHTS
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.base import Events, Trainer, all_active
from hfrl_torch.trainers.reference_policy import evaluate_placements


def oracle_noise(
    boards: int, frequency: float, consistency: float, generator: torch.Generator
) -> tuple[torch.Tensor, torch.Tensor]:
    """Griffith et al.'s two draws per board: whether the oracle speaks (probability L) and whether its
    judgement is flipped (probability 1 - C); always both, so a run is a function of its seed."""
    speaks = torch.rand(boards, generator=generator, dtype=torch.float64) < frequency
    flips = torch.rand(boards, generator=generator, dtype=torch.float64) >= consistency
    return speaks, flips


class OracleTrainer(Trainer):
    """Griffith et al.'s oracle over Dellacherie's reference policy (source ``"simulated:oracle"``).

    "The agent's placement is the reference's" means it leaves the same board (lines cleared included)
    as the reference's best placement: two placements that give the same afterstate are the same move to
    anyone watching the board, so both get +1. Draws come from one seeded generator, B uniforms for L and
    B for C at every step whatever happens, so a run is a function of its seed.

    :param frequency: L, the probability of giving feedback on a placement.
    :param consistency: C, the probability that the feedback is the oracle's judgement (else flipped).
    :param seed: seed of the trainer's generator.
    :param reaction: seconds between the placement and the event (> 0, so that ``PreviousStep`` credit
        goes to the placement judged; ``timing.HumanLikeTiming`` replaces it with random delays).
    :param weights: the reference's weights over the Dellacherie 6.
    :param log: feedback log every event is appended to.
    """

    source = "simulated:oracle"

    def __init__(
        self,
        frequency: float = 1.0,
        consistency: float = 1.0,
        seed: int = 0,
        reaction: float = 0.3,
        weights: tuple[float, ...] = DELLACHERIE_WEIGHTS,
        log: FeedbackLog | None = None,
    ) -> None:
        super().__init__(log)
        for name, v in (("frequency", frequency), ("consistency", consistency)):
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"{type(self).__name__} {name} must be within [0, 1], got {v!r}")
        if not reaction > 0:
            raise ValueError(f"{type(self).__name__} reaction must be > 0 seconds, got {reaction!r}")
        self.frequency = float(frequency)
        self.consistency = float(consistency)
        self.reaction = float(reaction)
        self.weights = tuple(weights)
        self.generator = torch.Generator().manual_seed(seed)

    def judge(
        self, obs: TensorDictBase, action: torch.Tensor, active: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The noiseless judgement: +1 where ``action`` [B] leaves the reference's board, else -1."""
        ref = evaluate_placements(obs, active, self.weights)
        same = ref.same_as_best.gather(-1, action.reshape(-1, 1).to(torch.int64).cpu()).squeeze(-1)
        return torch.where(same, 1.0, -1.0).to(torch.float64)

    def give(
        self,
        obs: TensorDictBase,
        action: torch.Tensor,
        time: float,
        episode: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> Events:
        act = all_active(obs, active)
        speaks, flips = oracle_noise(act.shape[0], self.frequency, self.consistency, self.generator)
        h = torch.where(flips, -1.0, 1.0) * self.judge(obs, action, act)
        return self._one_per_board(h, act & speaks, time + self.reaction, obs, episode)
