"""TAMER over primitive moves (thesis Algorithm 1): lookahead deltas and credit to the last move."""

from __future__ import annotations

import torch

from hfrl_torch.agents.tamer.primitive_tamer import PrimitiveTamerAgent
from hfrl_torch.envs.tetris import TetrisRules
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES
from hfrl_torch.envs.tetris.primitive import DROP, LEFT, RIGHT, PrimitiveTetris
from hfrl_torch.envs.tetris.sequence import game_key, piece_at
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.feedback.events import FeedbackEvent


def _game_with(piece: str, batch: int = 1) -> PrimitiveTetris:
    seed = next(s for s in range(10_000) if piece_at(game_key(s), 0, False) == PIECE_NAMES.index(piece))
    game = PrimitiveTetris(TetrisRules(10, 12), batch)
    game.reset(torch.ones(batch, dtype=torch.bool), torch.full((batch,), seed))
    return game


def test_ghost_deltas_move_the_landing_columns_and_drop_changes_nothing():
    agent = PrimitiveTamerAgent(_game_with("O"), alpha=0.1)
    d = agent.move_deltas()[0]
    heights = d[:, :10]  # the O spawns over columns 4-5 and would land on the floor there
    assert heights[LEFT].tolist() == [0, 0, 0, 2, 0, -2, 0, 0, 0, 0]
    assert heights[RIGHT].tolist() == [0, 0, 0, 0, -2, 0, 2, 0, 0, 0]
    assert torch.equal(d[DROP], torch.zeros_like(d[DROP]))
    visible = PrimitiveTamerAgent(_game_with("O"), alpha=0.1, view="visible").move_deltas()[0]
    assert visible[DROP, :10].abs().sum() > 0  # the dropped piece leaves the top: the shown board changes


def test_feedback_credits_the_last_move_and_steers_the_next():
    game = _game_with("O", batch=2)
    agent = PrimitiveTamerAgent(game, alpha=0.1)
    deltas = agent.move_deltas()
    action = agent.act(time=0.0)
    assert action.tolist() == [LEFT, LEFT]  # w = 0: every move ties, the first wins
    game.step(action)
    ev = FeedbackEvent(time=0.5, value=-1.0, source="simulated:oracle")
    channel = FeedbackChannel(2)
    channel.put_events([[ev], []])
    assert agent.learn(channel.deliver(1.0)).tolist() == [1, 0]
    assert torch.allclose(agent.model.weight[0], -0.1 * deltas[0, LEFT])
    assert torch.equal(agent.model.weight[1], torch.zeros_like(agent.model.weight[1]))
    assert agent.act(time=1.0)[0] != LEFT  # punished for moving left, it now prefers another move
