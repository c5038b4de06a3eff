"""Griffith et al.'s oracle on any task: the action taken is judged against a reference policy the user names.

A SIMULATED trainer, not a person. ``trainer.reference=<module:callable>`` is a function of an observation
batch ``[B, S]`` returning actions ``[B]`` (integers) or action values ``[B, A]``; the actions the reference
takes (every action of highest value, for values) are right. At each step, with probability L
(``frequency``) the oracle gives +1 for a right action and -1 otherwise, flipped with probability 1 - C
(``consistency``), ``reaction`` seconds later (``timing.HumanLikeTiming`` replaces that with human delays,
fatigue, bias and absences, as for the Tetris oracle).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.oracle import OracleTrainer

__all__ = ["Reference", "ReferenceOracle", "right_actions"]

Reference = Callable[[torch.Tensor], object]  # observations [B, S] -> actions [B] or values [B, A]


def right_actions(reference: Reference, obs: torch.Tensor, actions: int) -> torch.Tensor:
    """The actions ``[B, A]`` (bool) the reference takes in ``obs`` [B, S]: its action, or every action of its
    highest value; ``ValueError`` with one line if it returns anything else."""
    b = obs.shape[0]
    try:
        out = torch.as_tensor(reference(obs))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"failed on observations of shape {list(obs.shape)} ({exc})") from None
    if out.shape == torch.Size([b]) and not out.is_floating_point() and out.dtype != torch.bool:
        if bool(((out < 0) | (out >= actions)).any()):
            raise ValueError(f"returned actions {out.tolist()} outside 0..{actions - 1}")
        return torch.nn.functional.one_hot(out.to(torch.int64).cpu(), actions).to(torch.bool)
    if out.shape == torch.Size([b, actions]) and out.is_floating_point():
        values = out.detach().to(torch.float64).cpu()
        if not bool(torch.isfinite(values).all()):
            raise ValueError("returned values that are not finite")
        return values == values.max(-1, keepdim=True).values
    raise ValueError(
        f"returned {out.dtype} of shape {list(out.shape)} for {b} observations; allowed: integer actions "
        f"[{b}] or float action values [{b}, {actions}]"
    )


class ReferenceOracle(OracleTrainer):
    """The oracle against a reference policy on ``keys.OBSERVATION`` (source ``"simulated:oracle"``): Tetris's
    oracle, its draws and timing, with the judgement the reference's instead of Dellacherie's.

    :param reference: the policy judged against (see the module docstring).
    :param actions: A, the task's number of actions.
    :param frequency: L, the probability of giving feedback on a step.
    :param consistency: C, the probability that the feedback is the oracle's judgement (else flipped).
    :param seed: seed of the generator (B draws for L and B for C at every step, whatever happens).
    :param reaction: seconds between the step and the event (> 0).
    :param log: feedback log every event is appended to.
    """

    def __init__(
        self,
        reference: Reference,
        actions: int,
        frequency: float = 1.0,
        consistency: float = 1.0,
        seed: int = 0,
        reaction: float = 0.3,
        log: FeedbackLog | None = None,
    ) -> None:
        super().__init__(frequency, consistency, seed, reaction, log=log)
        self.reference, self.actions = reference, int(actions)

    def judge(
        self, obs: TensorDictBase, action: torch.Tensor, active: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The noiseless judgement [B]: +1 where ``action`` is one the reference takes, else -1."""
        right = right_actions(self.reference, obs.get(keys.OBSERVATION), self.actions)
        taken = right.gather(-1, action.reshape(-1, 1).to(torch.int64).cpu()).squeeze(-1)
        return torch.where(taken, 1.0, -1.0).to(torch.float64)
