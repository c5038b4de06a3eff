"""Q-learning over afterstate features: the TD update by hand, epsilon-greedy choice, learning, train.py."""

from __future__ import annotations

import json

import pytest
import torch

from hfrl_torch.agents.qlearning import LinearQLearning
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.envs.tetris import TetrisRules
from hfrl_torch.envs.tetris.engine_numba import play
from hfrl_torch.envs.tetris.features import BT
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.experiment.config import validate_train
from hfrl_torch.experiment.tetris_evaluation import evaluate_tetris

pytestmark = pytest.mark.usefixtures("one_thread")


def _f(rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


def test_td_update_matches_the_hand_computed_step():
    # four learners with the same weights w = (0.5, -1), b = 0.25; alpha 0.1, gamma 0.9
    q = LinearQLearning(2, learners=4, alpha=0.1, gamma=0.9)
    q.weight.copy_(_f([[0.5, -1.0]] * 4))
    q.bias.fill_(0.25)
    chosen = _f([[1.0, 2.0]] * 4)  # Q(s, a) = 0.5 - 2 + 0.25 = -1.25
    reward = _f([1.0, 2.0, 1.0, 1.0])
    # s' has two placements: f = (2, 0) -> Q 1.25 and f = (0, 1) -> Q -0.75
    nxt = _f([[[2.0, 0.0], [0.0, 1.0]]] * 4)
    mask = torch.ones(4, 2, dtype=torch.bool)
    terminal = torch.tensor([[False, False], [False, False], [True, False], [False, False]])
    terminated = torch.tensor([False, True, False, False])
    active = torch.tensor([True, True, True, False])
    delta = q.td_update(chosen, reward, nxt, mask, terminal, terminated, active)

    # learner 0: target 1 + 0.9 * 1.25 = 2.125, delta = 2.125 + 1.25 = 3.375
    # learner 1: the game ended, target = r = 2, delta = 3.25
    # learner 2: the best placement of s' ends the game, so max over the other: 1 + 0.9 * -0.75 = 0.325,
    #            delta = 1.575
    # learner 3: not active, no change
    assert delta.tolist() == pytest.approx([3.375, 3.25, 1.575, 0.0])
    expected_w = [[0.8375, -0.325], [0.825, -0.35], [0.6575, -0.685], [0.5, -1.0]]
    assert q.weight.tolist() == [pytest.approx(row) for row in expected_w]
    assert q.bias.tolist() == pytest.approx([0.5875, 0.575, 0.4075, 0.25])


def test_epsilon_greedy_keeps_to_allowed_placements_and_is_seeded():
    q = LinearQLearning(1, learners=2, alpha=0.1, gamma=0.9, seed=3)
    q.weight.fill_(1.0)
    feats = _f([[[1.0], [5.0], [3.0], [3.0]], [[2.0], [2.0], [1.0], [9.0]]])
    mask = torch.tensor([[True, True, True, False], [True, True, True, False]])
    terminal = torch.tensor([[False, True, False, False], [False, False, False, False]])
    # greedy: board 0 skips the game-ending 5.0, board 1 takes the first of the tied 2.0s (9.0 is masked)
    assert q.act(feats, mask, terminal, 0.0).tolist() == [2, 0]
    draws = torch.stack([q.act(feats, mask, terminal, 1.0) for _ in range(600)])
    counts0 = torch.bincount(draws[:, 0], minlength=4)
    counts1 = torch.bincount(draws[:, 1], minlength=4)
    assert counts0[1] == 0 and counts0[3] == 0 and counts1[3] == 0
    assert (counts0[[0, 2]] > 240).all() and (counts1[:3] > 150).all()  # uniform among the allowed
    again = LinearQLearning(1, learners=2, alpha=0.1, gamma=0.9, seed=3)
    again.weight.fill_(1.0)
    again.act(feats, mask, terminal, 0.0)
    assert torch.equal(torch.stack([again.act(feats, mask, terminal, 1.0) for _ in range(600)]), draws)


SMALL = ["agent=qlearning", "domain.width=6", "domain.height=8"]


def test_qlearning_learner_is_deterministic_and_counts_games(tmp_path, run_learner):
    over = [*SMALL, "agent.games=4", "agent.alpha=0.002", "agent.gamma=0.9", "agent.epsilon=0.2"]
    over += ["agent.learners=3", "seed=4", "domain.max_pieces=40", "agent.eval_games=0"]
    a, _ = run_learner(tmp_path / "a", *over)
    b, _ = run_learner(tmp_path / "b", *over)
    assert a.lines.shape == (3, 4) and torch.equal(a.lines, b.lines)
    assert torch.equal(a.agent_q.weight, b.agent_q.weight) and torch.equal(a.agent_q.bias, b.agent_q.bias)
    assert (a.pieces > 0).all() and (a.pieces <= 40).all()
    assert not torch.equal(a.agent_q.weight, torch.zeros_like(a.agent_q.weight))


def test_learned_policies_clear_clearly_more_lines_than_random_and_untrained_ones(tmp_path, run_learner):
    over = [*SMALL, "agent.games=100", "agent.alpha=0.003", "agent.gamma=0.9", "agent.epsilon=0.1"]
    out, _ = run_learner(
        tmp_path, *over, "agent.learners=10", "seed=0", "domain.max_pieces=2000", "agent.eval_games=0"
    )
    rules = TetrisRules(6, 8)
    seeds = torch.arange(500, 540)
    learned = torch.stack(
        [play(rules, BT, w, seeds, max_pieces=2000)[0] for w in out.agent_q.weight]
    ).double()
    zeros = torch.zeros(13)
    random_lines = play(rules, BT, zeros, seeds, random_policy=True)[0].double().mean()
    untrained = play(rules, BT, zeros, seeds)[0].double().mean()  # w = 0: always the first placement
    assert learned.mean() > 3.0 * max(random_lines, untrained)
    assert (learned.mean(1) > untrained).sum() >= 8  # most learners, not just a lucky few
    lines = out.lines.double()
    assert lines[:, -20:].mean() > 1.4 * lines[:, :10].mean()  # and they got better while training


def test_train_qlearning_writes_metrics_and_a_checkpoint_that_evaluate_plays(tmp_path, run_learner):
    over = [*SMALL, "agent.games=3", "agent.learners=2", "agent.eval_games=2", "domain.max_pieces=50"]
    _, final = run_learner(tmp_path, *over)
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["game"] for r in rows] == [1, 2, 3]
    assert final["eval/lines_per_game_mean"] == rows[-1]["eval/lines_per_game_mean"] >= 0
    assert "eval/greedy_lines_mean" in final and "train/td_error_mean" in rows[0]
    ckpt = load_checkpoint(tmp_path, domain="tetris", agent="qlearning")
    assert ckpt["policy"]["kind"] == "linear" and ckpt["policy"]["weights"].shape == (13,)
    assert torch.equal(ckpt["policy"]["weights"], ckpt["state"]["learner"]["weight"][0])
    res = evaluate_tetris(compose_config("evaluate", f"policy={tmp_path}", "games=3"), progress=False)
    assert res["games"] == 3 and res["board"] == "6x8" and res["max_pieces"] == 50


def test_a_resumed_run_equals_an_uninterrupted_one(tmp_path, run_learner):
    over = [*SMALL, "agent.learners=2", "agent.eval_games=0", "domain.max_pieces=60", "seed=2"]
    whole, _ = run_learner(tmp_path / "whole", *over, "agent.games=6")
    _, stopped = run_learner(tmp_path / "part", *over, "agent.games=6", stop_after=2)
    assert stopped is None and 2 <= len(load_checkpoint(tmp_path / "part")["history"]) < 6
    part, _ = run_learner(
        tmp_path / "part", *over, "agent.games=6", checkpoint=load_checkpoint(tmp_path / "part")
    )
    assert torch.equal(whole.lines, part.lines) and torch.equal(whole.agent_q.weight, part.agent_q.weight)
    assert (tmp_path / "whole" / "metrics.jsonl").read_text() == (
        tmp_path / "part" / "metrics.jsonl"
    ).read_text()


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("agent.gamma=1.5", "agent.gamma=1.5 is invalid: must be a finite number in 0.0..1.0"),
        ("agent.alpha=0", "agent.alpha=0 is invalid"),
        ("agent.features=abc", "agent.features='abc' is invalid; allowed: bt, knox, dellacherie, dt"),
        ("agent.games=0", "agent.games=0 is invalid: must be an integer >= 1"),
        ("trainer=oracle", "trainer='oracle' with agent=qlearning"),
    ],
)
def test_bad_values_fail_with_one_line(override, message):
    with pytest.raises(ConfigError) as info:
        validate_train(compose_config("train", "agent=qlearning", override))
    assert message in str(info.value) and "\n" not in str(info.value)
