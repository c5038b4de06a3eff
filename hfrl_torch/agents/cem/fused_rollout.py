"""Score CE candidates under fusion: each candidate's value R acts together with the person's model H^.

The rollout of CE + human feedback (thesis Figure 4.1): every candidate plays its games with
``a = argmax_a f(R, H^)``, R its own afterstate value and H^ the TAMER model learned so far, by the fusion's
decision rule at its current weight (trust factor, annealed or fixed), in the compiled games of
:mod:`hfrl_torch.fusion.compiled`. With ``reward_shaping`` the candidates act on R alone and are ranked on
the fusion's reward, ``lines + beta * sum H^`` over their games (Knox & Stone's R' = R + beta H^ over a game).
With ``searches_weight`` (``fusion.weight=adaptive``) each candidate's last entry is its own weight on H^,
clamped at 0: CE searches the weight together with R's, and the games' lines select both.
"""

from __future__ import annotations

import torch

from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.fusion.compiled import FusedGames, play_fused
from hfrl_torch.fusion.fusion import Fusion

# agent.rank_candidates: when CE's candidates play fused with H^ (conf/agent/cem.yaml says what each means)
CANDIDATE_RANKINGS = ("fused_while_teaching", "fused", "alone")


class FusedRollout:
    """A CE ``Rollout`` that fuses each candidate's R with ``human_weights`` through ``fusion``.

    Set :attr:`human_weights` (H^'s weights, [F_h]) before each CE iteration; :attr:`last` holds the latest
    games (match counts included, for the trust factor).

    :param rules: board and rule options.
    :param env_features: the CE value's feature set (``bt``), a prefix of ``human_features``.
    :param human_features: H^'s feature set (``knox`` or ``bt``).
    :param fusion: the one fusion component (rule, scale, weight).
    :param max_pieces: cap on placements per game (0: none).
    :param searches_weight: candidates carry their weight on H^ as a last entry (a decision-level rule).
    """

    def __init__(
        self,
        rules: TetrisRules,
        env_features: str,
        human_features: str,
        fusion: Fusion,
        max_pieces: int = 0,
        searches_weight: bool = False,
    ) -> None:
        if searches_weight and fusion.reward_rule != "none":
            raise ValueError(
                f"CE cannot search the weight of {fusion.reward_rule!r}: its fitness grows with the weight"
            )
        self.searches_weight = searches_weight
        self.rules = rules
        self.env_features = env_features
        self.human_features = human_features
        self.fusion = fusion
        self.max_pieces = max_pieces
        self.human_weights: torch.Tensor | None = None
        self.weight: float | None = None  # set: every game and reward at this weight on H^, not the fusion's
        self.last: FusedGames | None = None

    def __call__(self, weights: torch.Tensor, seeds: torch.Tensor) -> tuple[torch.Tensor, ...]:
        if self.human_weights is None:
            raise RuntimeError("FusedRollout.human_weights is unset: give it H^'s weights before playing")
        weight = self.weight
        if self.searches_weight:
            weights, searched = weights[:, :-1], weights[:, -1].clamp(min=0.0)
            weight = searched if weight is None else weight
        games = play_fused(
            self.rules,
            self.env_features,
            self.human_features,
            weights,
            self.human_weights,
            self.fusion,
            seeds,
            weight=weight,
            max_pieces=self.max_pieces,
        )
        self.last = games
        if self.fusion.reward_rule == "none":
            return games.lines, games.pieces, games.capped
        lines = games.lines.to(torch.float64).unsqueeze(-1)
        if self.weight is None:
            w = self.fusion.weight(torch.zeros(lines.shape[0], dtype=torch.int64))
        else:
            w = torch.full((lines.shape[0],), float(self.weight), dtype=torch.float64)
        fitness = self.fusion.reward(lines, games.human_return.unsqueeze(-1), w).squeeze(-1)
        return games.lines, games.pieces, games.capped, fitness
