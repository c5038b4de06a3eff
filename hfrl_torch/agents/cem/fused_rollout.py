"""Score CE candidates under fusion: each candidate's value R acts together with the person's model H^.

The rollout of CE + human feedback (thesis Figure 4.1): every candidate plays its games with
``a = argmax_a f(R, H^)``, R its own afterstate value and H^ the TAMER model learned so far, at the current
weight (trust factor, annealed or fixed). With ``reward_shaping`` the candidates act on R alone and are
ranked on ``lines + beta * sum H^`` of their games (Knox & Stone's R' = R + beta H^ over a whole game).
"""

from __future__ import annotations

import torch

from hfrl_torch.envs.tetris.fused_play import FusedGames, play_fused
from hfrl_torch.envs.tetris.rules import TetrisRules


class FusedRollout:
    """A CE ``Rollout`` that fuses each candidate's R with ``human_weights`` at ``weight``.

    Set :attr:`human_weights` (H^'s weights, [F_h]) and :attr:`weight` before each CE iteration;
    :attr:`last` holds the latest games (match counts included, for the trust factor).

    :param rules: board and rule options.
    :param env_features: the CE value's feature set (``bt``), a prefix of ``human_features``.
    :param human_features: H^'s feature set (``knox`` or ``bt``).
    :param scheme: fusion scheme (a key of ``fused_play.RULES``).
    :param normalise: rescale R and H^ to [0, 1] per decision before fusing.
    :param max_pieces: cap on placements per game (0: none).
    """

    def __init__(
        self,
        rules: TetrisRules,
        env_features: str,
        human_features: str,
        scheme: str,
        normalise: bool = True,
        max_pieces: int = 0,
    ) -> None:
        self.rules = rules
        self.env_features = env_features
        self.human_features = human_features
        self.scheme = scheme
        self.normalise = normalise
        self.max_pieces = max_pieces
        self.human_weights: torch.Tensor | None = None
        self.weight = 0.0
        self.last: FusedGames | None = None

    def __call__(self, weights: torch.Tensor, seeds: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if self.human_weights is None:
            raise RuntimeError("FusedRollout.human_weights is unset: give it H^'s weights before playing")
        games = play_fused(
            self.rules,
            self.env_features,
            self.human_features,
            weights,
            self.human_weights,
            self.scheme,
            self.weight,
            seeds,
            normalise=self.normalise,
            max_pieces=self.max_pieces,
        )
        self.last = games
        if self.scheme == "reward_shaping":
            return games.lines, games.pieces, games.capped, self.weight * games.human_return
        return games.lines, games.pieces, games.capped
