"""Value-proxy trainer: feedback is the sign (or a scaled amount) of the change of a heuristic's board value.

A simulated trainer, not a person. The heuristic is Dellacherie's: his weights over the Dellacherie
features of the board alone (row and column transitions, holes, wells; landing height and eroded cells
describe a move, not a board, and are left out unless ``placement_terms``). The feedback on a
placement is ``sign(V(after) - V(before))``; no change gives no feedback.
"""

from __future__ import annotations

import math

import torch
from tensordict import TensorDictBase

from hfrl_torch.envs.tetris.features import DELLACHERIE_WEIGHTS
from hfrl_torch.feedback.events import MAX_ABS_FEEDBACK
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.base import Events, Trainer, all_active
from hfrl_torch.trainers.reference_policy import evaluate_placements

MODES = ("sign", "scaled")


class ValueProxyTrainer(Trainer):
    """Feedback from the change of Dellacherie's board value (source ``"simulated:value_proxy"``).

    :param mode: ``"sign"`` gives +1 / -1; ``"scaled"`` gives ``scale * change``, clipped to the largest
        value a ``FeedbackEvent`` holds.
    :param scale: the factor of ``"scaled"``.
    :param placement_terms: add the placement's landing-height and eroded-cells terms to V(after)
        (Dellacherie's full evaluation of the move).
    :param reaction: seconds between the placement and the event (> 0).
    :param weights: the heuristic's weights over the Dellacherie 6.
    :param log: feedback log every event is appended to.
    """

    source = "simulated:value_proxy"

    def __init__(
        self,
        mode: str = "sign",
        scale: float = 1.0,
        placement_terms: bool = False,
        reaction: float = 0.3,
        weights: tuple[float, ...] = DELLACHERIE_WEIGHTS,
        log: FeedbackLog | None = None,
    ) -> None:
        super().__init__(log)
        if mode not in MODES:
            raise ValueError(f"ValueProxyTrainer mode={mode!r} is invalid; allowed: {', '.join(MODES)}")
        if not (math.isfinite(scale) and scale > 0):
            raise ValueError(f"ValueProxyTrainer scale must be a finite number > 0, got {scale!r}")
        if not reaction > 0:
            raise ValueError(f"ValueProxyTrainer reaction must be > 0 seconds, got {reaction!r}")
        self.mode = mode
        self.scale = float(scale)
        self.placement_terms = placement_terms
        self.reaction = float(reaction)
        self.weights = tuple(weights)

    def value_change(
        self, obs: TensorDictBase, action: torch.Tensor, active: torch.Tensor | None = None
    ) -> torch.Tensor:
        """V(after) - V(before) [B] of placing ``action`` [B] on the boards of ``obs``."""
        ref = evaluate_placements(obs, active, self.weights)
        after = ref.value if self.placement_terms else ref.board_value
        chosen = after.gather(-1, action.reshape(-1, 1).to(torch.int64).cpu()).squeeze(-1)
        return chosen - ref.board_value_before

    def give(
        self,
        obs: TensorDictBase,
        action: torch.Tensor,
        time: float,
        episode: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> Events:
        act = all_active(obs, active)
        change = self.value_change(obs, action, act)
        if self.mode == "sign":
            h = torch.sign(change)
        else:
            h = (self.scale * change).clamp(-MAX_ABS_FEEDBACK, MAX_ABS_FEEDBACK)
        return self._one_per_board(h, act & (h != 0), time + self.reaction, obs, episode)
