"""TAMER for Tetris placements: greedy choice, deltas, credit of the feedback the channel delivers, learning
from an oracle through train.py's loop."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.agents.tamer import TamerAgent, placement_deltas
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.engine_numba import play
from hfrl_torch.envs.tetris.features import BT
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.feedback.credit import GammaDelay, credit_weights
from hfrl_torch.feedback.events import FeedbackEvent


def _obs(after, state, mask, terminal=None) -> TensorDict:
    after = torch.as_tensor(after, dtype=torch.float32)
    b, a, _ = after.shape
    return TensorDict(
        {
            keys.AFTERSTATE_FEATURES: after,
            keys.STATE_FEATURES: torch.as_tensor(state, dtype=torch.float32),
            keys.ACTION_MASK: torch.as_tensor(mask, dtype=torch.bool),
            keys.AFTERSTATE_TERMINAL: torch.zeros(b, a, dtype=torch.bool)
            if terminal is None
            else torch.as_tensor(terminal, dtype=torch.bool),
        },
        batch_size=[b],
    )


def _ev(time: float, value: float) -> FeedbackEvent:
    return FeedbackEvent(time=time, value=value, source="simulated:oracle")


def test_greedy_respects_mask_ties_and_terminal():
    agent = TamerAgent(1, learners=3, alpha=0.1)
    agent.model.weight.fill_(1.0)
    obs = _obs(
        [[[1.0], [5.0], [5.0], [9.0]], [[2.0], [2.0], [2.0], [2.0]], [[1.0], [5.0], [3.0], [9.0]]],
        [[0.0], [0.0], [0.0]],
        [[True, True, True, False], [False, True, True, True], [True, True, True, True]],
        [[False] * 4, [False] * 4, [False, True, False, True]],
    )
    # board 0: 9.0 is masked, 5.0 ties -> first; board 1: all tie -> first valid; board 2: best non-terminal
    assert agent.act(obs).tolist() == [1, 1, 2]
    all_terminal = _obs([[[1.0], [3.0]]], [[0.0]], [[False, True]], [[True, True]])
    assert TamerAgent(1, learners=1, alpha=0.1).act(all_terminal).tolist() == [
        1
    ]  # only game-ending ones left


def test_deltas_are_afterstate_minus_state_on_the_env():
    env = TetrisEnv(batch=2, rules=TetrisRules(10, 12), features="knox", seed=4)
    td = env.reset()
    for _ in range(6):
        td[keys.ACTION] = torch.zeros(2, dtype=torch.int64)
        td = env.step(td)["next"]
    phi = placement_deltas(td)
    assert phi.shape == (2, env.num_actions, 46) and phi.dtype == torch.float64
    expect = td[keys.AFTERSTATE_FEATURES].double() - td[keys.STATE_FEATURES].double().unsqueeze(1)
    assert torch.equal(phi, expect)
    assert phi[td[keys.ACTION_MASK]].abs().sum() > 0


def test_feedback_waits_for_its_time_and_credits_the_placement_just_made():
    agent = TamerAgent(2, learners=2, alpha=0.5)
    obs = _obs(
        [[[1.0, 0.0], [0.0, 1.0]], [[2.0, 2.0], [0.0, 0.0]]], [[0.0, 0.0], [1.0, 1.0]], [[True, True]] * 2
    )
    agent.record(obs, torch.tensor([1, 0]), time=0.0)
    obs2 = _obs(
        [[[3.0, 3.0], [0.0, 0.0]], [[5.0, 0.0], [0.0, 0.0]]], [[0.0, 0.0], [0.0, 0.0]], [[True, True]] * 2
    )
    agent.record(obs2, torch.tensor([0, 0]), time=1.0)
    # board 0: an event at 0.5 judges the first placement (phi [0, 1]); board 1: at 1.2, the second
    channel = FeedbackChannel(2)
    channel.put_events([[_ev(0.5, 1.0)], [_ev(1.2, -1.0), _ev(7.0, 1.0)]])
    assert agent.learn(channel.deliver(0.9)).tolist() == [1, 0]
    assert torch.allclose(agent.model.weight[0], torch.tensor([0.0, 0.5], dtype=torch.float64))
    assert torch.equal(agent.model.weight[1], torch.zeros(2, dtype=torch.float64))
    assert agent.learn(channel.deliver(2.0)).tolist() == [0, 1]
    assert torch.allclose(agent.model.weight[1], torch.tensor([-2.5, 0.0], dtype=torch.float64))
    assert channel.pending == 1 and agent.applied.tolist() == [1, 1]


def test_gamma_credit_spreads_over_recent_placements():
    delay = GammaDelay(2.0, 0.28)
    agent = TamerAgent(1, learners=1, alpha=1.0, credit=delay, window=None)
    for k, f in enumerate([1.0, 10.0, 100.0]):
        agent.record(_obs([[[f]]], [[0.0]], [[True]]), torch.tensor([0]), time=0.2 * k)
    channel = FeedbackChannel(1)
    channel.put_events([[_ev(0.65, 1.0)]])
    agent.learn(channel.deliver(1.0))
    c = credit_weights(0.65, [0.0, 0.2, 0.4], [0.2, 0.4, float("inf")], delay, window=None)
    assert agent.model.weight.item() == pytest.approx(
        float(c @ torch.tensor([1.0, 10.0, 100.0], dtype=torch.float64))
    )


def test_tamer_learner_is_deterministic_and_counts_games(tmp_path, run_learner):
    over = ["agent=tamer", "trainer=oracle", "agent.games=3", "agent.learners=3", "seed=5", "domain.width=8"]
    over += ["domain.height=8", "domain.max_pieces=300", "human.alpha=0.001", "trainer.timing.enabled=false"]
    a, final = run_learner(tmp_path / "a", *over)
    b, _ = run_learner(tmp_path / "b", *over)
    assert a.lines.shape == (3, 3) and torch.equal(a.lines, b.lines)
    assert torch.equal(a.human.model.weight, b.human.model.weight)
    assert (a.pieces > 0).all() and (a.pieces <= 300).all()
    given = a.given.sum(1)
    assert torch.equal(given[:, 0], given[:, 1] + given[:, 2]) and (a.human.applied <= given[:, 0]).all()
    # L = 0.5: about half of the placements get feedback
    rate = given[:, 0].sum() / a.pieces.sum()
    assert 0.4 < rate < 0.6
    assert final["game"] == 3 and final["feedback_events"] == float(given[:, 0].sum())


def test_oracle_trained_tamer_clears_clearly_more_lines_than_untrained(tmp_path, run_learner):
    over = ["agent=tamer", "trainer=oracle", "agent.games=5", "agent.learners=10", "seed=0"]
    over += [
        "domain.max_pieces=400",  # a taught game may go on for thousands: 400 pieces tell it from untaught
        "human.alpha=0.001",
        "trainer.frequency=1.0",
        "trainer.consistency=1.0",
    ]
    learner, _ = run_learner(tmp_path, *over, "trainer.timing.enabled=false")
    lines = learner.lines.double()
    first, later = lines[:, 0].mean(), lines[:, 2:].mean()
    rules = TetrisRules(10, 10)
    seeds = torch.arange(100, 150)
    random_lines, _, _ = play(rules, BT, torch.zeros(21), seeds, random_policy=True)
    untrained, _, _ = play(rules, BT, torch.zeros(21), seeds)  # w = 0: always the first placement
    assert later > 2.0 * first
    print(f"first {float(first):.1f}, later {float(later):.1f} lines")
    assert later > 10.0 * max(random_lines.double().mean(), untrained.double().mean(), 0.5)
