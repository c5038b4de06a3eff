"""Policy gradient over a softmax of afterstate values: score, Fisher matrix and both updates by hand,
seeded sampling, learning, train.py."""

from __future__ import annotations

import json
import math

import pytest
import torch

from hfrl_torch.agents.pg import PolicyGradient, natural_direction, score_and_fisher
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


# one board, four placements: two allowed with f = (1, 0) and (0, 2), a game-ending one, an invalid one
FEATS = _f([[[1.0, 0.0], [0.0, 2.0], [9.0, 9.0], [5.0, 5.0]]])
MASK = torch.tensor([[True, True, True, False]])
TERMINAL = torch.tensor([[False, False, True, False]])
ALLOWED = MASK & ~TERMINAL


def test_score_and_fisher_by_hand():
    # theta = (ln 3, 0), T = 1: logits (ln 3, 0) -> pi = (0.75, 0.25), fbar = (0.75, 0.5)
    theta = _f([[math.log(3.0), 0.0]])
    score, fisher = score_and_fisher(FEATS, ALLOWED, torch.tensor([1]), theta, 1.0)
    assert score.tolist() == [pytest.approx([-0.75, 1.5])]  # f_1 - fbar
    # Cov = p (1 - p) d d^T with d = f_0 - f_1 = (1, -2): 0.1875 * [[1, -2], [-2, 4]]
    assert fisher[0].tolist() == [pytest.approx([0.1875, -0.375]), pytest.approx([-0.375, 0.75])]
    # temperature 2 halves the logits and divides the score by 2: pi = (sqrt 3, 1) / (sqrt 3 + 1)
    score2, fisher2 = score_and_fisher(FEATS, ALLOWED, torch.tensor([0]), theta, 2.0)
    p0 = math.sqrt(3.0) / (math.sqrt(3.0) + 1.0)
    assert score2.tolist() == [pytest.approx([(1 - p0) / 2, -2 * (1 - p0) / 2])]
    assert fisher2[0, 0, 0].item() == pytest.approx(p0 * (1 - p0) / 4)
    pg = PolicyGradient(2, 1, lr=0.1)
    pg.weight.copy_(theta)
    assert pg(FEATS, MASK, TERMINAL).exp().tolist() == [pytest.approx([0.75, 0.25, 0.0, 0.0])]


def test_reinforce_update_by_hand():
    # lr 0.1, two games per update, baseline decay 0.5; theta = 0, so pi = (0.5, 0.5) and fbar = (0.5, 1)
    pg = PolicyGradient(2, 1, lr=0.1, games_per_update=2, baseline_decay=0.5)
    one = torch.tensor([True])
    pg.record(FEATS, MASK, TERMINAL, torch.tensor([0]), one)  # score (0.5, -1)
    assert pg.end_games(one, _f([3.0])).tolist() == [False]  # return 3, baseline 0: (G - b) z = (1.5, -3)
    assert pg.weight.tolist() == [[0.0, 0.0]] and pg.baseline.tolist() == [3.0]
    pg.record(FEATS, MASK, TERMINAL, torch.tensor([1]), one)  # score (-0.5, 1)
    assert pg.end_games(one, _f([1.0])).tolist() == [True]  # return 1, baseline 3: (-2) z = (1, -2)
    # theta = 0.1 * ((1.5, -3) + (1, -2)) / 2
    assert pg.weight.tolist() == [pytest.approx([0.125, -0.25])]
    # baseline (0.5 * 3 + 1) / (0.5 * 1 + 1) = 5 / 3
    assert pg.baseline.tolist() == [pytest.approx(5.0 / 3.0)] and pg.updates.tolist() == [1]


def test_learners_learn_only_from_their_own_games():
    pg = PolicyGradient(2, 2, lr=0.1)
    feats, mask, terminal = FEATS.expand(2, -1, -1), MASK.expand(2, -1), TERMINAL.expand(2, -1)
    pg.record(feats, mask, terminal, torch.tensor([0, 1]), torch.tensor([True, False]))  # learner 1 idle
    assert pg.end_games(torch.tensor([True, False]), _f([3.0, 5.0])).tolist() == [True, False]
    assert pg.weight.tolist() == [pytest.approx([0.15, -0.3]), [0.0, 0.0]]  # 0.1 * 3 * (0.5, -1)
    assert pg.baseline.tolist() == [3.0, 0.0] and pg.game_score.abs().sum() == 0


def test_natural_gradient_is_the_damped_fisher_inverse_times_the_vanilla_one():
    theta = _f([[math.log(3.0), 0.0]])
    # a game of two placements: the one above (taking f = (0, 2)), then (1, 1) vs (0, 0) taking (1, 1)
    second = _f([[[1.0, 1.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]])
    second_mask = torch.tensor([[True, True, False, False]])
    no_end = torch.zeros(1, 4, dtype=torch.bool)
    steps = []
    for natural in (False, True):
        pg = PolicyGradient(2, 1, lr=0.5, natural=natural, damping=0.5)
        pg.weight.copy_(theta)
        pg.record(FEATS, MASK, TERMINAL, torch.tensor([1]), None)
        pg.record(second, second_mask, no_end, torch.tensor([0]), None)
        pg.end_games(torch.tensor([True]), _f([2.0]))
        steps.append((pg.weight - theta)[0] / 0.5)
    vanilla, natural = steps
    # z = (-0.75, 1.5) + 0.25 * (1, 1) = (-0.5, 1.75); g = (G - 0) z = (-1, 3.5)
    assert vanilla.tolist() == pytest.approx([-1.0, 3.5])
    # F = 0.1875 * ([[1, -2], [-2, 4]] + [[1, 1], [1, 1]]) = [[0.375, -0.1875], [-0.1875, 0.9375]]
    # F + 0.5 I = [[0.875, -0.1875], [-0.1875, 1.4375]], det = 1.2578125 - 0.03515625 = 1.22265625
    # (F + 0.5 I)^-1 g = [[1.4375, 0.1875], [0.1875, 0.875]] (-1, 3.5) / det = (-0.78125, 2.875) / det
    assert natural.tolist() == pytest.approx([-0.78125 / 1.22265625, 2.875 / 1.22265625])
    fisher = _f([[[0.375, -0.1875], [-0.1875, 0.9375]]])
    assert natural_direction(vanilla.unsqueeze(0), fisher, 0.5)[0].tolist() == pytest.approx(natural.tolist())


def test_sampling_keeps_to_allowed_placements_and_is_seeded():
    feats = FEATS.expand(2, -1, -1)
    mask, terminal = MASK.expand(2, -1), TERMINAL.expand(2, -1)
    a = PolicyGradient(2, 2, lr=0.1, seed=7)
    a.weight.copy_(_f([[math.log(3.0), 0.0], [0.0, 0.0]]))
    draws = torch.stack([a.act(feats, mask, terminal) for _ in range(800)])
    assert set(draws.flatten().tolist()) == {0, 1}
    share = (draws == 0).double().mean(0)
    assert abs(share[0] - 0.75) < 0.06 and abs(share[1] - 0.5) < 0.06
    b = PolicyGradient(2, 2, lr=0.1, seed=7)
    b.weight.copy_(a.weight)
    assert torch.equal(torch.stack([b.act(feats, mask, terminal) for _ in range(800)]), draws)


SMALL = ["agent=pg", "domain.width=6", "domain.height=8"]


def test_pg_learner_is_deterministic_and_counts_games(tmp_path, run_learner):
    over = [
        *SMALL,
        "agent.games=4",
        "agent.lr=0.003",
        "agent.learners=3",
        "seed=4",
        "agent.games_per_update=2",
    ]
    over += ["domain.max_pieces=40", "agent.eval_games=0"]
    a, _ = run_learner(tmp_path / "a", *over)
    b, _ = run_learner(tmp_path / "b", *over)
    assert a.lines.shape == (3, 4) and torch.equal(a.lines, b.lines)
    assert torch.equal(a.pg.weight, b.pg.weight) and a.pg.updates.tolist() == [2, 2, 2]
    assert (a.pieces > 0).all() and (a.pieces <= 40).all()


@pytest.mark.parametrize(("natural", "lr", "per_update"), [(False, 0.003, 1), (True, 1.0, 5)])
def test_learned_policies_clear_clearly_more_lines_than_random_and_untrained_ones(
    tmp_path, run_learner, natural, lr, per_update
):
    over = [
        *SMALL,
        "agent.games=100",
        f"agent.lr={lr}",
        "agent.learners=10",
        "seed=0",
        f"agent.natural={natural}",
    ]
    over += [f"agent.games_per_update={per_update}", "domain.max_pieces=2000", "agent.eval_games=0"]
    out, _ = run_learner(tmp_path, *over)
    rules = TetrisRules(6, 8)
    seeds = torch.arange(500, 540)
    learned = torch.stack([play(rules, BT, w, seeds, max_pieces=2000)[0] for w in out.pg.weight]).double()
    zeros = torch.zeros(13)
    random_lines = play(rules, BT, zeros, seeds, random_policy=True)[0].double().mean()
    untrained = play(rules, BT, zeros, seeds)[0].double().mean()  # w = 0: always the first placement
    assert learned.mean() > 2.5 * max(random_lines, untrained)
    assert (learned.mean(1) > untrained).sum() >= 8  # most learners, not just a lucky few
    lines = out.lines.double()  # the stochastic policies got better while training
    assert lines[:, -20:].mean() > 2.0 * lines[:, :10].mean()


def test_train_pg_writes_metrics_and_a_checkpoint_that_evaluate_plays(tmp_path, run_learner):
    over = [*SMALL, "agent.games=3", "agent.learners=2", "agent.natural=true", "agent.eval_games=2"]
    _, final = run_learner(tmp_path, *over, "domain.max_pieces=50")
    rows = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [r["game"] for r in rows] == [1, 2, 3]
    assert final["eval/lines_per_game_mean"] == rows[-1]["eval/lines_per_game_mean"] >= 0
    assert "eval/greedy_lines_ci95_high" in final
    ckpt = load_checkpoint(tmp_path, domain="tetris", agent="pg")
    assert ckpt["policy"]["kind"] == "linear" and ckpt["policy"]["weights"].shape == (13,)
    assert torch.equal(ckpt["policy"]["weights"], ckpt["state"]["learner"]["weight"][0])
    res = evaluate_tetris(compose_config("evaluate", f"policy={tmp_path}", "games=3"), progress=False)
    assert res["games"] == 3 and res["board"] == "6x8" and res["max_pieces"] == 50


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("agent.lr=-1", "agent.lr=-1 is invalid"),
        ("agent.natural=maybe", "agent.natural='maybe' is invalid: must be true or false"),
        ("agent.damping=0", "agent.damping=0 is invalid"),
        ("agent.temperature=0", "agent.temperature=0 is invalid"),
        ("agent.games_per_update=0", "agent.games_per_update=0 is invalid: must be an integer >= 1"),
        ("agent.baseline_decay=2", "agent.baseline_decay=2 is invalid"),
        (
            "fusion=linear trainer=none",
            "fusion='linear' fuses a trainer's H^ into the policy; choose a trainer",
        ),
        ("fusion=exponential trainer=oracle", "fusion='exponential' with agent=pg is invalid; allowed: none"),
        ("fusion=linear trainer=oracle human.features=bt", "agent=pg with a trainer needs"),
    ],
)
def test_bad_values_fail_with_one_line(override, message):
    args = (
        ["agent=pg", "agent.natural=true", override]
        if "damping" in override
        else ["agent=pg", *override.split()]
    )
    with pytest.raises(ConfigError) as info:
        validate_train(compose_config("train", *args))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_fused_values_shift_the_policy_and_the_score_is_taken_under_it():
    weight = _f([[0.0, 0.0]])
    values = _f([[0.0, math.log(3.0), 0.0, 0.0]])  # theta . f = 0, H^ likes placement 1: p = (1/4, 3/4)
    score, fisher = score_and_fisher(FEATS, ALLOWED, torch.tensor([0]), weight, 1.0, values=values)
    fbar = 0.25 * _f([1.0, 0.0]) + 0.75 * _f([0.0, 2.0])
    torch.testing.assert_close(score[0], _f([1.0, 0.0]) - fbar)
    torch.testing.assert_close(fisher[0], 3 / 16 * _f([[1.0, -2.0], [-2.0, 4.0]]))  # p0 p1 (f0-f1)(f0-f1)^T
    agent = PolicyGradient(2, 1, 0.1)
    p = agent(FEATS, MASK, TERMINAL, values).exp()[0]
    torch.testing.assert_close(p[:2], _f([0.25, 0.75]))


def test_pg_with_a_simulated_trainer_learns_h_and_updates_trust_per_learner(tmp_path, run_learner):
    over = [
        *SMALL,
        "fusion=linear",
        "fusion.weight=trust",
        "trainer=oracle",
        "agent.games=6",
        "agent.learners=3",
        "agent.eval_games=0",
    ]
    _, final = run_learner(tmp_path, *over)
    rows = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert rows[0]["fusion/weight_mean"] == 0.5 and rows[-1]["fusion/weight_mean"] != 0.5
    assert all(0.0 <= r["fusion/match_rate_mean"] <= 1.0 for r in rows)
    assert sum(r["feedback/given_mean"] for r in rows) > 0 and final["eval/lines_per_game_mean"] >= 0
    events = (tmp_path / "feedback.jsonl").read_text().splitlines()
    assert len(events) > 10 and '"simulated:oracle"' in events[-1]


@pytest.mark.parametrize("weight", ["trust", "adaptive"])
def test_a_resumed_taught_run_equals_an_uninterrupted_one(tmp_path, run_learner, weight):
    over = [*SMALL, "fusion=linear", "trainer=oracle", "agent.learners=2", "agent.eval_games=0", "seed=1"]
    over += [f"fusion.weight={weight}"]
    over += ["domain.max_pieces=60"]
    whole, _ = run_learner(tmp_path / "whole", *over, "agent.games=6")
    _, stopped = run_learner(tmp_path / "part", *over, "agent.games=6", stop_after=2)
    assert stopped is None and 2 <= len(load_checkpoint(tmp_path / "part")["history"]) < 6
    part, _ = run_learner(
        tmp_path / "part", *over, "agent.games=6", checkpoint=load_checkpoint(tmp_path / "part")
    )
    assert torch.equal(whole.lines, part.lines) and torch.equal(whole.pg.weight, part.pg.weight)
    assert torch.equal(whole.human.model.weight, part.human.model.weight)
    assert (tmp_path / "whole" / "metrics.jsonl").read_text() == (
        tmp_path / "part" / "metrics.jsonl"
    ).read_text()
    events = [(tmp_path / d / "feedback.jsonl").read_text().splitlines() for d in ("whole", "part")]
    # the same events (a resumed log holds a second session header, and its events carry its session name)
    body = [[e.split('"session"')[0] for e in log if '"schema"' not in e] for log in events]
    assert body[0] == body[1]
