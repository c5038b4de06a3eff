"""A trainer restored from its state_dict gives the same feedback as one that never stopped."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.trainers import HumanLikeTiming, OracleTrainer


def _make() -> HumanLikeTiming:
    return HumanLikeTiming(
        OracleTrainer(frequency=0.6, consistency=0.8, seed=3), absence=0.3, tail_lines=5.0, seed=4
    )


def _play(trainer: HumanLikeTiming, env: TetrisEnv, steps: int, start: int) -> list[tuple]:
    td = env.reset(env.reset().set(keys.RESET_GAME_SEED, torch.arange(3)))
    out = []
    for i in range(steps):
        action = torch.zeros(3, dtype=torch.int64)
        evs = trainer.give(td, action, float(start + i), torch.full((3,), (start + i) // 5))
        out.append([[(e.time, e.value, e.step) for e in b] for b in evs])
        if i % 5 == 4:
            trainer.end_games(torch.tensor([True, False, True]), torch.tensor([2, 0, 7]))
    return out


def test_restored_trainer_continues_its_draws():
    env = TetrisEnv(batch=3, rules=TetrisRules(width=6, height=8), features="bt", seed=0)
    whole = _make()
    _play(whole, env, 12, 0)
    state = whole.state_dict()
    expected = _play(whole, env, 12, 12)

    resumed = _make()
    resumed.load_state_dict(state)
    assert _play(resumed, env, 12, 12) == expected
    assert any(any(b) for step in expected for b in step)  # the check compares real events


def test_state_of_another_trainer_is_refused():
    with pytest.raises(CheckpointError, match="bad OracleTrainer state"):
        OracleTrainer().load_state_dict({"given": 0})
