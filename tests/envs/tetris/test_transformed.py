"""TetrisEnv under TorchRL transforms: random actions follow the placements' mask through TorchRL's
``ActionMask`` wherever it sits among the transforms, in rollouts, ``check_env_specs`` and a collector's
random frames; without it the error names it."""

from __future__ import annotations

import pytest
import torch
from torchrl.collectors import Collector
from torchrl.envs import ActionMask, Compose, RewardSum, StepCounter, TransformedEnv
from torchrl.envs.utils import check_env_specs

from hfrl_torch import keys
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules

RULES = TetrisRules(6, 8)


def _env(*transforms) -> TransformedEnv:
    return TransformedEnv(TetrisEnv(batch=3, rules=RULES, seed=0), Compose(*transforms))


def _valid(td) -> bool:
    """Every action taken on a live board was a valid placement of its observation."""
    chosen = td[keys.ACTION_MASK].gather(-1, td[keys.ACTION].unsqueeze(-1)).squeeze(-1)
    return bool(chosen.all())


@pytest.mark.parametrize("mask_first", [True, False])
def test_a_random_rollout_with_step_counter_and_reward_sum(mask_first):
    torch.manual_seed(0)
    others = [StepCounter(), RewardSum()]
    env = _env(ActionMask(), *others) if mask_first else _env(*others, ActionMask())
    td = env.rollout(200, break_when_any_done=False)  # several games per board, partial resets
    assert td.shape == (3, 200) and _valid(td)
    assert int(td["next", keys.DONE].sum()) >= 3
    steps = td["next", keys.STEP_COUNT].squeeze(-1)
    done = td["next", keys.DONE].squeeze(-1)
    assert bool((steps[done] >= 1).all()) and int(steps.max()) > 1
    episode = td["next", keys.EPISODE_REWARD].squeeze(-1)
    assert torch.equal(episode[done], td["next", keys.LINES].squeeze(-1)[done].float())


def test_appended_later_and_check_env_specs():
    env = TransformedEnv(TetrisEnv(batch=2, rules=RULES, seed=1), StepCounter())
    env.append_transform(ActionMask())
    check_env_specs(env, seed=0)
    torch.manual_seed(1)
    assert _valid(env.rollout(100, break_when_any_done=False))


def test_a_collectors_random_frames_follow_the_mask():
    torch.manual_seed(2)
    env = _env(StepCounter(), ActionMask())

    def first_valid(td):
        return td.set(keys.ACTION, td[keys.ACTION_MASK].to(torch.int8).argmax(-1))

    collector = Collector(env, first_valid, frames_per_batch=60, total_frames=180, init_random_frames=120)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 3 and all(_valid(b) for b in batches)
    assert int(sum(b["next", keys.DONE].sum() for b in batches[:2])) >= 1  # the random frames crossed resets


def test_without_action_mask_the_error_names_it():
    torch.manual_seed(0)
    with pytest.raises(ValueError, match=r"is not a valid placement .* need torchrl's ActionMask\(\)"):
        _env(StepCounter()).rollout(200)


def test_the_bare_env_keeps_its_own_mask():
    torch.manual_seed(3)
    assert _valid(TetrisEnv(batch=2, rules=RULES, seed=2).rollout(100, break_when_any_done=False))
