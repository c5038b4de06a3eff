"""TetrisEnv: specs, partial resets, determinism, masks and errors."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

import hfrl_torch  # noqa: F401  (registers the Gymnasium ids)
from hfrl_torch import keys
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.models.linear import batched_values, greedy_placement


def _greedy_bt(td):
    # fewer holes and a lower, flatter stack: a simple fixed BT policy
    f = td[keys.AFTERSTATE_FEATURES]
    w = torch.zeros(f.shape[-1], dtype=torch.float64)
    w[-1], w[-2] = -10.0, -1.0
    w[10:19] = -1.0
    v = batched_values(w.expand(f.shape[0], -1), f)
    return greedy_placement(v, td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL])


@pytest.mark.parametrize("features", ["bt", "knox", "dellacherie", "dt"])
@pytest.mark.parametrize("preview", [False, True])
def test_check_env_specs(features, preview):
    env = TetrisEnv(batch=3, rules=TetrisRules(8, 8, preview=preview), features=features)
    check_env_specs(env, seed=0)


def test_shapes_and_mask_of_first_piece():
    env = TetrisEnv(batch=5, rules=TetrisRules(10, 20))
    td = env.reset()
    assert td[keys.AFTERSTATE_FEATURES].shape == (5, 34, 21)
    assert td[keys.BOARD].shape == (5, 20, 10)
    counts = {0: 17, 1: 9, 2: 34, 3: 17, 4: 17, 5: 34, 6: 34}
    for piece, n in zip(td[keys.PIECE].tolist(), td[keys.ACTION_MASK].sum(-1).tolist(), strict=True):
        assert n == counts[piece]


def test_partial_reset_only_touches_flagged_boards():
    env = TetrisEnv(batch=4, rules=TetrisRules(10, 10), seed=1)
    td = env.reset()
    for _ in range(5):
        td[keys.ACTION] = _greedy_bt(td)
        td = env.step(td)["next"]
    before = td.clone()
    reset_td = td.clone().set(keys.RESET, torch.tensor([[True], [False], [True], [False]]))
    after = env.reset(reset_td)
    assert not after[keys.BOARD][0].any() and not after[keys.BOARD][2].any()
    assert after[keys.PIECES_PLACED][[0, 2]].eq(0).all()
    for k in (keys.BOARD, keys.PIECE, keys.PIECES_PLACED, keys.GAME_SEED, keys.AFTERSTATE_FEATURES):
        assert torch.equal(after[k][[1, 3]], before[k][[1, 3]]), k
    assert before[keys.PIECES_PLACED][[1, 3]].eq(5).all()


def test_same_seed_same_games_and_given_game_seed():
    def play(seed, game_seeds=None):
        env = TetrisEnv(batch=3, rules=TetrisRules(10, 10), seed=seed)
        td = (
            env.reset()
            if game_seeds is None
            else env.reset(env.reset().set(keys.RESET_GAME_SEED, game_seeds))
        )
        total = torch.zeros(3)
        pieces = []
        for _ in range(40):
            td[keys.ACTION] = _greedy_bt(td)
            out = env.step_and_maybe_reset(td)
            total += out[0]["next", keys.REWARD].squeeze(-1)
            pieces.append(out[1][keys.PIECE].clone())
            td = out[1]
        return total, torch.stack(pieces)

    a, pa = play(7)
    b, pb = play(7)
    _, pc = play(8)
    assert torch.equal(a, b) and torch.equal(pa, pb)
    assert not torch.equal(pa, pc)
    seeds = torch.tensor([11, 12, 13])
    d, pd = play(0, seeds)
    e, pe = play(99, seeds)
    assert torch.equal(pd, pe) and torch.equal(d, e)


def test_game_over_sets_done_and_terminated():
    env = TetrisEnv(batch=2, rules=TetrisRules(4, 4), seed=0)
    td = env.reset()
    done_seen = torch.zeros(2, dtype=torch.bool)
    for _ in range(30):
        td[keys.ACTION] = torch.zeros(2, dtype=torch.int64)  # always the leftmost placement: tops out fast
        nxt = env.step(td)["next"]
        done_seen |= nxt[keys.DONE].squeeze(-1)
        assert torch.equal(nxt[keys.DONE], nxt[keys.TERMINATED] | nxt[keys.TRUNCATED])
        if done_seen.all():
            break
        td = nxt
    assert done_seen.all()


def test_max_pieces_truncates():
    env = TetrisEnv(batch=2, rules=TetrisRules(10, 20), max_pieces=3)
    td = env.reset()
    for i in range(3):
        td[keys.ACTION] = _greedy_bt(td)
        td = env.step(td)["next"]
        assert td[keys.TRUNCATED].all() == (i == 2)
    assert not td[keys.TERMINATED].any()


def test_invalid_action_raises_with_the_allowed_values():
    env = TetrisEnv(batch=2, rules=TetrisRules(10, 10), seed=0)
    td = env.reset()
    n = td[keys.ACTION_MASK].sum(-1)
    td[keys.ACTION] = torch.stack([torch.tensor(0), n[1]])  # board 1: one past its last placement
    if n[1] < 34:
        with pytest.raises(ValueError, match="not a valid placement"):
            env.step(td)


def test_reward_counts_lines_and_lines_key_accumulates():
    env = TetrisEnv(batch=8, rules=TetrisRules(6, 10), seed=3)
    td = env.reset()
    got = torch.zeros(8)
    for _ in range(60):
        td[keys.ACTION] = _greedy_bt(td)
        nxt = env.step(td)["next"]
        alive = ~td[keys.DONE].squeeze(-1) if keys.DONE in td else torch.ones(8, dtype=torch.bool)
        got += nxt[keys.REWARD].squeeze(-1) * alive
        assert torch.equal(nxt[keys.LINES], td[keys.LINES] + nxt[keys.REWARD].long() * alive.unsqueeze(-1))
        td = nxt
    assert got.sum() > 0


def test_gymnasium_registration_and_checker():
    from gymnasium.utils.env_checker import check_env

    env = gym.make("hfrl_torch/Tetris-v0", width=8, height=8, render_mode="rgb_array")
    check_env(env.unwrapped)
    obs, _ = env.reset(seed=1)
    assert obs[keys.AFTERSTATE_FEATURES].shape == (26, 17)  # T, L, J: 6 + 7 + 6 + 7 on 8 wide
    frame = env.render()
    assert frame.shape == (8 * 16, 8 * 16, 3) and frame.dtype == np.uint8


def test_greedy_placement_avoids_losing_moves_but_scores_the_best_one_when_all_lose():
    values = torch.tensor([[5.0, 1.0, 3.0, 9.0], [5.0, 1.0, 7.0, 2.0]], dtype=torch.float64)
    mask = torch.tensor([[True, True, True, False], [True, True, True, True]])
    terminal = torch.tensor([[True, False, False, False], [True, True, True, True]])
    # board 0: the best non-terminal valid placement (2); board 1: all lose, so the best of them (2)
    assert greedy_placement(values, mask, terminal).tolist() == [2, 2]
    assert greedy_placement(values, mask).tolist() == [0, 2]


def test_partial_reset_with_the_current_data_starts_new_games():
    # TorchRL's convention passes the current tensordict (with its game_seed observation) plus "_reset"
    env = TetrisEnv(batch=2, rules=TetrisRules(10, 10), seed=5)
    td = env.reset()
    old = td[keys.GAME_SEED].clone()
    after = env.reset(td.clone().set(keys.RESET, torch.tensor([[True], [False]])))
    assert after[keys.GAME_SEED][0] != old[0] and after[keys.GAME_SEED][1] == old[1]


def test_each_observation_owns_its_action_mask():
    # the engine reuses its buffers; a stored observation must keep the mask of its own piece
    env = TetrisEnv(batch=2, rules=TetrisRules(10, 10), seed=2)
    td = env.reset()
    first = td[keys.ACTION_MASK].clone()
    stored = td[keys.ACTION_MASK]
    for _ in range(4):
        td[keys.ACTION] = _greedy_bt(td)
        td = env.step(td)["next"]
    assert torch.equal(stored, first)
    counts = {0: 17, 1: 9, 2: 34, 3: 17, 4: 17, 5: 34, 6: 34}
    assert td[keys.ACTION_MASK].sum(-1).tolist() == [counts[p] for p in td[keys.PIECE].tolist()]


def test_weights_of_the_wrong_length_are_refused():
    from hfrl_torch.envs.tetris.engine_numba import play

    with pytest.raises(ValueError, match=r"allowed: \[21\] or \[2, 21\]"):
        play(TetrisRules(10, 10), 0, torch.zeros(9), torch.arange(2))


def test_linear_value_module_plays_the_engines_game():
    # the torch module scoring the env's observation picks what the compiled whole-game kernel picks
    from hfrl_torch.envs.tetris.engine_numba import play
    from hfrl_torch.envs.tetris.features import DELLACHERIE, DELLACHERIE_WEIGHTS
    from hfrl_torch.models import LinearValue

    value = LinearValue(6)
    with torch.no_grad():
        value.linear.weight.copy_(torch.tensor([DELLACHERIE_WEIGHTS], dtype=torch.float64))
    env = TetrisEnv(batch=1, rules=TetrisRules(10, 10), features="dellacherie")
    td = env.reset(env.reset().set(keys.RESET_GAME_SEED, torch.tensor([77])))
    for _ in range(150):
        values = value(td[keys.AFTERSTATE_FEATURES])
        td[keys.ACTION] = greedy_placement(values, td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL])
        td = env.step(td)["next"]
        assert not td[keys.DONE].any()
    lines, pieces, capped = play(
        TetrisRules(10, 10),
        DELLACHERIE,
        torch.tensor(DELLACHERIE_WEIGHTS),
        torch.tensor([77]),
        max_pieces=150,
    )
    assert bool(capped[0]) and int(pieces[0]) == 150
    assert int(td[keys.LINES][0, 0]) == int(lines[0]) > 0
