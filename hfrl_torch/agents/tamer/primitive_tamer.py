"""TAMER over primitive moves (left, right, rotate, drop): the thesis's Algorithm 1 on ``PrimitiveTetris``.

Knox & Stone 2009; the thesis's Algorithms 1-3. Each step the agent looks one move ahead: for each of
the four moves it simulates the move on a copy of the boards and scores the change of the board
features, f(s_{t+1,a}) - f(s_t), with H^; it takes the best move. Feedback received since the last step
is credited to the last move through its delta f_{t-1} - f_{t-2} (``PreviousStep`` credit).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from hfrl_torch.agents.tamer.tamer import TamerAgent
from hfrl_torch.envs.tetris.engine_torch import board_features_t
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.envs.tetris.primitive import DROP, NUM_ACTIONS, PrimitiveTetris
from hfrl_torch.feedback.credit import CreditModel

VIEWS = ("ghost", "visible")
_STATE = ("cells", "pieces", "keys", "index", "rot", "row", "col", "alive")


def copy_boards(game: PrimitiveTetris, repeat: int) -> PrimitiveTetris:
    """A new ``PrimitiveTetris`` holding each board of ``game`` ``repeat`` times in a row (for lookahead)."""
    out = PrimitiveTetris(game.rules, game.batch * repeat, game.device)
    for name in _STATE:
        setattr(out, name, getattr(game, name).repeat_interleave(repeat, dim=0).clone())
    return out


def board_feature_vectors(cells: torch.Tensor, fid: int) -> torch.Tensor:
    """BT or Knox features [N, F] (float64) of boards of cells [N, H, W]."""
    n, h, _ = cells.shape
    levels = torch.arange(1, h + 1, device=cells.device).view(1, h, 1)
    heights = (cells.to(torch.int64) * levels).amax(dim=1)
    filled = cells.flatten(1).sum(-1)
    zeros = torch.zeros(n, dtype=torch.float64, device=cells.device)
    return board_features_t(fid, h, heights, filled, zeros, zeros, None, torch.float64)


class PrimitiveTamerAgent:
    """TAMER on primitive moves, one learner per board (Knox & Stone 2009; thesis Algorithm 1).

    The board whose features are taken is, with ``view="ghost"`` (default), the stack with the falling
    piece dropped from where it is: the placement the piece is heading for, so that a move changes the
    features by what it changes about that placement. ``view="visible"`` takes the board as shown
    (stack and falling piece), the literal reading of Algorithm 1, under which most moves change
    only the floating piece's columns.

    :param features: ``bt`` (the thesis's 21) or ``knox`` (46).
    """

    def __init__(
        self,
        game: PrimitiveTetris,
        alpha: float,
        features: str = "bt",
        view: str = "ghost",
        credit: CreditModel | None = None,
    ) -> None:
        if view not in VIEWS:
            raise ValueError(f"PrimitiveTamerAgent view={view!r} is invalid; allowed: {', '.join(VIEWS)}")
        if features not in ("bt", "knox"):
            raise ValueError(f"PrimitiveTamerAgent features={features!r} is invalid; allowed: bt, knox")
        self.fid = feature_id(features)
        self.game = game
        self.view = view
        self.tamer = TamerAgent(feature_size(self.fid, game.rules.width), game.batch, alpha, credit)

    @property
    def model(self) -> torch.nn.Module:
        return self.tamer.model

    def features(self, game: PrimitiveTetris, locked: torch.Tensor | None = None) -> torch.Tensor:
        """f(s) [N, F] of every board of ``game`` under this agent's view; ``locked`` [N] marks boards whose
        piece has just locked, whose ghost is the locked stack itself (not the next piece's drop)."""
        if self.view == "visible":
            return board_feature_vectors(game.cells | game.falling_cells(), self.fid)
        ghost = copy_boards(game, 1)
        ghost.step(torch.full((ghost.batch,), DROP, device=ghost.device))
        f = board_feature_vectors(ghost.cells, self.fid)
        if locked is not None:
            f = torch.where(locked.view(-1, 1), board_feature_vectors(game.cells, self.fid), f)
        return f

    def move_deltas(self) -> torch.Tensor:
        """f(s_{t+1,a}) - f(s_t) [B, 4, F] for the four moves (Algorithm 3), simulated on copies.

        Under the ghost view a drop changes nothing (delta 0): it makes the ghost real.
        """
        now = self.features(self.game)
        ahead = copy_boards(self.game, NUM_ACTIONS)
        _, locked = ahead.step(torch.arange(NUM_ACTIONS, device=ahead.device).repeat(self.game.batch))
        after = self.features(ahead, locked).view(self.game.batch, NUM_ACTIONS, -1)
        return after - now.unsqueeze(1)

    def act(self, time: float, active: torch.Tensor | None = None) -> torch.Tensor:
        """Choose each board's move greedily under H^ (the first on ties) and remember its delta."""
        deltas = self.move_deltas()
        action = self.model(deltas).argmax(-1)
        chosen = deltas.gather(1, action.view(-1, 1, 1).expand(-1, 1, deltas.shape[-1])).squeeze(1)
        self.tamer.record_phi(chosen, time, active)
        return action

    def learn(self, feedback: TensorDictBase) -> torch.Tensor:
        """Learn from the feedback channel's entries (``keys.FEEDBACK*``) for the last moves (Algorithm 2);
        returns how many events each board learned from [B]."""
        return self.tamer.learn(feedback)
