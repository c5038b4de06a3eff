"""The compiled twin of the fusion component against the engine, and against the TorchRL env choosing through
``FusionModule``: the same rule codes and weights, the same choices, the same match counts."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch import keys
from hfrl_torch.agents.cem.fused_rollout import FusedRollout
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.engine_numba import play
from hfrl_torch.envs.tetris.features import BT
from hfrl_torch.fusion import Fusion, FusionModule, as_schedule
from hfrl_torch.fusion.compiled import play_fused
from hfrl_torch.fusion.schemes import COMPILED_RULES, OPTIONS

RULES = TetrisRules(width=8, height=8)


def _weights(n: int, f: int, seed: int) -> torch.Tensor:
    return torch.randn(n, f, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) * 5


def _fusion(option: str, weight: float = 0.5, scaling: str = "decision") -> Fusion:
    return Fusion.from_option(option, as_schedule(weight), scaling=scaling)


def test_rule_codes_come_from_the_component():
    import hfrl_torch.fusion.compiled as compiled

    assert tuple(COMPILED_RULES[k] for k in ("none", "human_only", "linear")) == (
        compiled.ENV_ONLY,
        compiled.HUMAN_ONLY,
        compiled.ADDITIVE,
    )
    assert (
        COMPILED_RULES["exponential"],
        COMPILED_RULES["control_sharing"],
    ) == (compiled.EXPONENTIAL, compiled.CONTROL_SHARING)
    for option, rules in OPTIONS.items():
        assert _fusion(option).compiled_rule == COMPILED_RULES[rules.decision]


@pytest.mark.parametrize("bag", [False, True])
def test_env_only_rule_plays_the_engines_games(bag):
    rules = TetrisRules(width=8, height=8, bag=bag)
    env_w, seeds = _weights(24, 17, 0), torch.arange(24)
    ref = play(rules, BT, env_w, seeds)
    got = play_fused(rules, "bt", "knox", env_w, torch.zeros(38), _fusion("none"), seeds)
    assert torch.equal(got.lines, ref[0]) and torch.equal(got.pieces, ref[1])
    assert got.lines.sum() > 0


def test_h_over_feature_changes_acts_as_the_same_afterstate_policy():
    """argmax_a h . (f(s'_a) - f(s)) = argmax_a h . f(s'_a): H^ with R's weights plays R's games."""
    env_w, seeds = _weights(16, 17, 1), torch.arange(100, 116)
    human = torch.cat([env_w, torch.zeros(16, 38 - 17, dtype=torch.float64)], 1)
    by_env = play_fused(RULES, "bt", "knox", env_w, human, _fusion("none"), seeds)
    by_human = play_fused(RULES, "bt", "knox", env_w, human, _fusion("human_only"), seeds)
    assert torch.equal(by_env.lines, by_human.lines) and torch.equal(by_env.pieces, by_human.pieces)
    assert torch.equal(by_env.matches, by_env.compared)  # the two argmaxes agree wherever H^ prefers one
    assert int(by_env.compared.sum()) > 0.9 * int(by_env.pieces.sum())


@pytest.mark.parametrize(
    ("option", "weight"),
    [("linear", 0.7), ("exponential", 1.5), ("reward_shaping", 0.2), ("annealed", 0.4), ("human_only", 0.0)],
)
def test_kernel_chooses_and_counts_as_the_env_through_the_fusion_module(option, weight):
    """The same games through TetrisEnv (knox features) + FusionModule and through the kernel, with one
    Fusion: the same placements, lines, H^ returns and match counts."""
    boards, cap = 4, 40
    env_w = _weights(1, 17, 2)[0]
    human_w = _weights(1, 38, 3)[0] / 10
    env = TetrisEnv(batch=boards, rules=RULES, features="knox", max_pieces=cap, seed=0)
    seeds = torch.arange(7, 7 + boards)
    td = env.reset(env.reset().set(keys.RESET_GAME_SEED, seeds))
    fusion = Fusion.from_option(option, as_schedule([weight] * boards), scaling="decision")
    choose = FusionModule(fusion, select="greedy")
    lines = torch.zeros(boards, dtype=torch.int64)
    pieces = torch.zeros(boards, dtype=torch.int64)
    human_return = torch.zeros(boards, dtype=torch.float64)
    compared = torch.zeros(boards, dtype=torch.int64)
    matches = torch.zeros(boards, dtype=torch.int64)
    alive = torch.ones(boards, dtype=torch.bool)
    while bool(alive.any()):
        td.set(keys.ENV_VALUES, (td[keys.AFTERSTATE_FEATURES][..., :17].double() * env_w).sum(-1))
        td.set(keys.HUMAN_VALUES, (placement_deltas(td) * human_w).sum(-1))
        before = fusion.matches.state_dict()
        action = choose(td)[keys.ACTION]
        matches += torch.where(alive, fusion.matches.matches - before["matches"], 0)
        compared += torch.where(alive, fusion.matches.compared - before["compared"], 0)
        h = td[keys.HUMAN_VALUES]
        human_return += torch.where(alive, h.gather(1, action.view(-1, 1)).squeeze(1), 0.0)
        td[keys.ACTION] = action
        td = env.step(td)
        done = td["next", keys.DONE].view(-1)
        ended = alive & done
        lines[ended] = td["next", keys.LINES].view(-1)[ended]
        pieces[ended] = td["next", keys.PIECES_PLACED].view(-1)[ended]
        alive &= ~done
        td = td["next"]
    got = play_fused(RULES, "bt", "knox", env_w, human_w, _fusion(option, weight), seeds, max_pieces=cap)
    assert torch.equal(got.lines, lines) and torch.equal(got.pieces, pieces)
    torch.testing.assert_close(got.human_return, human_return)
    assert torch.equal(got.matches, matches) and torch.equal(got.compared, compared)
    assert int(compared.sum()) > 0


def test_control_sharing_follows_h_with_probability_beta():
    env_w, seeds = _weights(8, 17, 4), torch.arange(8)
    human = torch.cat([-env_w, torch.zeros(8, 38 - 17, dtype=torch.float64)], 1)  # H^ wants the opposite of R
    never = play_fused(RULES, "bt", "knox", env_w, human, _fusion("control_sharing", 0.0), seeds)
    plain = play_fused(RULES, "bt", "knox", env_w, human, _fusion("none"), seeds)
    always = play_fused(RULES, "bt", "knox", env_w, human, _fusion("control_sharing", 1.0), seeds)
    by_human = play_fused(RULES, "bt", "knox", env_w, human, _fusion("human_only"), seeds)
    assert torch.equal(never.lines, plain.lines) and torch.equal(never.pieces, plain.pieces)
    assert torch.equal(always.pieces, by_human.pieces)


def test_reward_shaping_ranks_on_lines_plus_beta_sum_h():
    rollout = FusedRollout(RULES, "bt", "knox", _fusion("reward_shaping", 0.25), max_pieces=30)
    rollout.human_weights = _weights(1, 38, 5)[0]
    lines, _, capped, fitness = rollout(_weights(6, 17, 6), torch.arange(6))
    assert rollout.last is not None
    torch.testing.assert_close(fitness, lines.double() + 0.25 * rollout.last.human_return)
    assert torch.equal(lines, rollout.last.lines) and capped.dtype == torch.bool
    rollout.weight = 0.0  # the candidates on R alone (agent.rank_candidates): ranked on their lines alone
    lines, _, _, fitness = rollout(_weights(6, 17, 6), torch.arange(6))
    assert torch.equal(fitness, lines.double())


def test_a_set_weight_overrides_the_searched_one():
    """``FusedRollout.weight`` (CE's candidates on R alone) plays every candidate at that weight, whatever
    weight on H^ it carries as its last entry (``fusion.weight=search``)."""
    rollout = FusedRollout(RULES, "bt", "knox", _fusion("linear"), max_pieces=30, searches_weight=True)
    rollout.human_weights = _weights(1, 38, 5)[0]
    env_w, seeds = _weights(6, 17, 6), torch.arange(6)
    searched = torch.cat([env_w, torch.full((6, 1), 3.0, dtype=torch.float64)], 1)
    rollout.weight = 0.0
    alone = rollout(searched, seeds)[0]
    plain = play_fused(
        RULES, "bt", "knox", env_w, rollout.human_weights, _fusion("none"), seeds, max_pieces=30
    )
    assert torch.equal(alone, plain.lines)
    rollout.weight = None
    assert not torch.equal(rollout(searched, seeds)[1], plain.pieces)  # the searched weight 3 plays H^


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"env_features": "dt"}, "env_features='dt' is invalid for fused play; allowed: bt, knox"),
        ({"weight": -1.0}, "fusion weight must be finite and >= 0"),
        ({"scaling": "spread"}, "scaling none, decision, not 'spread'"),
    ],
)
def test_bad_arguments_fail_with_one_line(kwargs, message):
    args = {"env_features": "bt", "weight": 0.5, "scaling": "decision"}
    args.update(kwargs)
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        play_fused(
            RULES,
            args["env_features"],
            "knox",
            torch.zeros(17),
            torch.zeros(38),
            _fusion("linear", scaling=args["scaling"]),
            torch.arange(2),
            weight=args["weight"],
        )


def test_unset_human_weights_is_an_error():
    with pytest.raises(RuntimeError, match="human_weights is unset"):
        FusedRollout(RULES, "bt", "knox", _fusion("linear"))(torch.zeros(1, 17), torch.arange(1))
