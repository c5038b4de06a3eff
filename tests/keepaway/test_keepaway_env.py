"""The TorchRL and Gymnasium environments, determinism, rendering and the benchmark runner."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from hfrl_torch import keys
from hfrl_torch.envs.keepaway import (
    ENV_ID,
    EPISODE_END_REWARDS,
    KeepawayConfig,
    KeepawayEnv,
    KeepawaySimulator,
    play_benchmark_policy,
    register_keepaway,
    render_rgb,
    write_gif,
)
from hfrl_torch.envs.keepaway.referee import END_TAKEN


@pytest.mark.parametrize(
    "options", [{}, {"preset": "rcss19", "decision_period_cycles": 5}, {"keepers": 4, "takers": 3}]
)
def test_check_env_specs(options: dict) -> None:
    check_env_specs(KeepawayEnv(3, seed=1, **options))


def test_partial_reset_changes_only_flagged_fields() -> None:
    env = KeepawayEnv(4, seed=2)
    td = env.reset()
    td = env.rand_step(td)
    before = env.sim.state.clone()
    obs_before = td["next", keys.OBSERVATION].clone()
    flags = torch.tensor([True, False, True, False]).unsqueeze(-1)
    after = env.reset(td["next"].clone().set(keys.RESET, flags))
    state = env.sim.state
    for i in (1, 3):
        assert torch.equal(state.pos[i], before.pos[i])
        assert torch.equal(after[keys.OBSERVATION][i], obs_before[i])
    for i in (0, 2):
        assert not torch.equal(state.pos[i], before.pos[i])
        assert not after[keys.DONE][i].item()


def _episode(seed: int) -> list[tuple[int, float, int]]:
    env = KeepawayEnv(1, seed=seed)
    td = env.reset()
    trace = []
    for step in range(400):
        td.set(keys.ACTION, torch.tensor([step % 3]))
        out = env.step(td)["next"]
        trace.append((int(out[keys.KEEPER]), float(out[keys.REWARD]), int(out[keys.EPISODE_CYCLES])))
        if out[keys.DONE].item():
            break
        td = out
    return trace


def test_same_seed_same_episode() -> None:
    assert _episode(5) == _episode(5)
    assert _episode(5) != _episode(6)


def test_rewards_count_cycles_per_keeper() -> None:
    env = KeepawayEnv(4, seed=3)
    td = env.reset()
    last = {b: {int(td[keys.KEEPER][b]): int(td[keys.EPISODE_CYCLES][b])} for b in range(4)}
    checked = ended = 0
    gen = torch.Generator().manual_seed(0)
    for _ in range(30):
        td.set(keys.ACTION, torch.randint(0, 3, (4,), generator=gen))
        out = env.step(td)["next"]
        for b in range(4):
            cycles = int(out[keys.EPISODE_CYCLES][b])
            if bool(out[keys.DONE][b]):
                end_rewards = out[EPISODE_END_REWARDS][b]
                for k in range(3):
                    assert end_rewards[k].item() == (cycles - last[b][k] if k in last[b] else 0)
                assert out[keys.REWARD][b].item() == cycles - max(last[b].values())
                assert out[keys.END_CAUSE][b].item() in (1, 2)
                ended += 1
            else:
                k = int(out[keys.KEEPER][b])
                assert out[keys.REWARD][b].item() == cycles - last[b].get(k, cycles)
                last[b][k] = cycles
                checked += 1
        if out[keys.DONE].any():
            done = out[keys.DONE].clone()
            out = env.reset(out.clone().set(keys.RESET, done))
            for b in done.squeeze(-1).nonzero().flatten().tolist():
                last[b] = {int(out[keys.KEEPER][b]): int(out[keys.EPISODE_CYCLES][b])}
        td = out
    assert checked > 20 and ended >= 1


def test_decision_period_makes_holds_last_five_cycles() -> None:
    env = KeepawayEnv(4, seed=4, decision_period_cycles=5)
    td = env.reset()
    td.set(keys.ACTION, torch.zeros(4, dtype=torch.long))
    out = env.step(td)["next"]
    same_keeper = out[keys.KEEPER] == td[keys.KEEPER]
    alive = ~out[keys.DONE].squeeze(-1)
    assert (out["step_cycles"][same_keeper & alive] >= 5).all()


def test_gym_registration_is_idempotent_and_env_runs() -> None:
    register_keepaway()
    register_keepaway()
    env = gymnasium.make(ENV_ID, render_mode="rgb_array", keepers=4, takers=3)
    obs, info = env.reset(seed=0)
    assert obs.shape == (19,)
    assert env.action_space.n == 4
    total = 0.0
    for _ in range(300):
        obs, reward, terminated, _, info = env.step(0)
        total += reward
        if terminated:
            break
    assert terminated and info["end_cause"] in (1, 2)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3


def test_render_and_gif(tmp_path) -> None:
    sim = KeepawaySimulator(2, KeepawayConfig(keepers=5, takers=4), seed=0)
    frame = render_rgb(sim.state, 1, sim.config)
    assert frame.shape[2] == 3 and frame.dtype == np.uint8
    assert (frame == np.array([220, 40, 40], dtype=np.uint8)).all(-1).any()  # takers drawn
    path = write_gif([frame, render_rgb(sim.state, 0, sim.config)], tmp_path / "ep.gif")
    assert path.stat().st_size > 0


def test_benchmark_runner_fields() -> None:
    result = play_benchmark_policy("hold", 12, batch=6, progress=False)
    assert set(result) == {
        "domain",
        "policy",
        "preset",
        "keepers",
        "takers",
        "episodes",
        "mean_s",
        "sd_s",
        "median_s",
        "ci95_low",
        "ci95_high",
        "taken_share",
        "out_share",
        "cycles_per_s",
    }
    assert result["domain"] == "keepaway" and result["episodes"] == 12
    assert result["ci95_low"] <= result["mean_s"] <= result["ci95_high"]
    assert result["taken_share"] + result["out_share"] == pytest.approx(1.0)
    assert 0.5 < result["mean_s"] < 20.0


@pytest.mark.parametrize("keepers,takers", [(4, 3), (5, 4)])
def test_larger_teams_play_episodes(keepers: int, takers: int) -> None:
    result = play_benchmark_policy("random", 8, keepers=keepers, takers=takers, batch=8, progress=False)
    assert result["episodes"] == 8 and result["mean_s"] > 0.5


@pytest.mark.parametrize("preset", ["2005", "rcss19"])
def test_always_hold_episodes_are_taken_within_a_bounded_time(preset: str) -> None:
    """Always Hold against the takers must end, mostly by a turnover, within seconds (the
    reference HoldBall side rule froze it in a turn-only cycle, docs/keepaway.md item 14)."""
    sim = KeepawaySimulator(64, KeepawayConfig(preset=preset), seed=7)
    ended = torch.zeros(64, dtype=torch.bool)
    cause = torch.zeros(64, dtype=torch.long)
    for _ in range(200):
        out = sim.step(torch.zeros(64, dtype=torch.long), active=~ended)
        cause = torch.where(out.ended, out.end_cause, cause)
        ended |= out.ended
        if bool(ended.all()):
            break
    assert bool(ended.all())
    assert (cause == END_TAKEN).float().mean().item() > 0.6
