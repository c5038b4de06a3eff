"""The TorchRL and Gymnasium environments, determinism, rendering and the benchmark runner."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import check_env_specs

from hfrl_torch import keys
from hfrl_torch.envs.keepaway import (
    ENV_ID,
    EPISODE_END_REWARDS,
    TASKS,
    KeepawayConfig,
    KeepawayEnv,
    KeepawaySimulator,
    hand_coded_actions,
    make_benchmark_policy,
    play_benchmark_policy,
    register_keepaway,
    render_rgb,
    write_gif,
)
from hfrl_torch.envs.keepaway.referee import END_TAKEN

torch.set_num_threads(1)
SYNCS = ("all", "any")


SERVER = TASKS["server"]
EXACT = TASKS["exact"]  # the exact-state task, which these tests were written on


@pytest.mark.parametrize("sync", SYNCS)
@pytest.mark.parametrize(
    "options",
    [
        EXACT,
        {"preset": "rcss19", "decision_period_cycles": 5, **EXACT},
        {"keepers": 4, "takers": 3, **EXACT},
        SERVER,
        {"keepers": 4, "takers": 3, "decision_period_cycles": 5, **SERVER},
        {"kernels": "cycle", **SERVER},
        {"kernels": "cycle", "keepers": 4, "takers": 3, "decision_period_cycles": 5, **EXACT},
        {"kernels": "cycle", "cycle_by_cycle": True, "decision_period_cycles": 5, **SERVER},
    ],
)
def test_check_env_specs(options: dict, sync: str) -> None:
    check_env_specs(KeepawayEnv(3, seed=1, sync=sync, **options))


@pytest.mark.parametrize(
    "options",
    [EXACT, SERVER, {"kernels": "cycle", **SERVER}, {"kernels": "cycle", "cycle_by_cycle": True, **SERVER}],
)
@pytest.mark.parametrize("sync", SYNCS)
def test_partial_reset_changes_only_flagged_fields(sync: str, options: dict) -> None:
    env = KeepawayEnv(4, seed=2, sync=sync, **options)
    td = env.reset()
    td = env.rand_step(td)
    before = env.sim.state.clone()
    obs_before = td["next", keys.OBSERVATION].clone()
    deciding_before = td["next", keys.DECIDING].clone()
    flags = torch.tensor([True, False, True, False]).unsqueeze(-1)
    after = env.reset(td["next"].clone().set(keys.RESET, flags))
    state = env.sim.state
    for i in (1, 3):
        for name, value in state.tensors().items():
            assert torch.equal(value[i], getattr(before, name)[i]), name
        assert torch.equal(after[keys.OBSERVATION][i], obs_before[i])
        assert after[keys.DECIDING][i].item() == deciding_before[i].item()
    for i in (0, 2):
        assert not torch.equal(state.pos[i], before.pos[i])
        assert not after[keys.DONE][i].item()
        # "all": run to the keeper's first decision inside reset; "any": not deciding yet, no cycle run
        assert after[keys.DECIDING][i].item() == (sync == "all")
        assert (after[keys.EPISODE_CYCLES][i].item() == 0) == (sync == "any")


# at B = 1 every reset restarts every field: TorchRL's other branch (the env's own code, alike on every
# kernel: run on the fast compiled cycle only)
@pytest.mark.parametrize(
    ("options", "batch"),
    [(EXACT, 6), ({"kernels": "cycle", **SERVER}, 6), ({"kernels": "cycle", **SERVER}, 1)],
)
@pytest.mark.parametrize("sync", SYNCS)
def test_maybe_reset_gives_what_torchrl_s_blend_gives(sync: str, options: dict, batch: int) -> None:
    """KeepawayEnv.maybe_reset puts the reset's entries in place; TorchRL's (here through a TransformedEnv,
    as on the taught learners' path) blends them with TensorDict.where: twin envs, the same actions, the
    same tensordicts at every step, with an entry of the user's own in the root as well."""
    ours = KeepawayEnv(batch, seed=4, sync=sync, **options)
    theirs = TransformedEnv(KeepawayEnv(batch, seed=4, sync=sync, **options))
    td_ours, td_theirs = ours.reset(), theirs.reset()
    generator = torch.Generator().manual_seed(0)
    resets = 0
    # "all" runs each step to every field's next decision: 40 steps of 6 fields see 13 or more resets,
    # 120 steps 7 or more in the other cases
    for _ in range(40 if sync == "all" and batch > 1 else 120):
        action = torch.randint(0, ours.config.num_actions, (batch,), generator=generator)
        extra = torch.full((batch, 2), 7.0)
        td_ours[keys.ACTION], td_theirs[keys.ACTION] = action, action.clone()
        td_ours["extra"], td_theirs["extra"] = extra, extra.clone()
        out_ours, td_ours = ours.step_and_maybe_reset(td_ours)
        out_theirs, td_theirs = theirs.step_and_maybe_reset(td_theirs)
        resets += int(out_ours["next", keys.DONE].any())
        for a, b in ((out_ours, out_theirs), (td_ours, td_theirs)):
            assert set(a.keys(True, True)) == set(b.keys(True, True))
            assert all(torch.equal(a[k], b[k]) for k in b.keys(True, True)), sorted(b.keys(True, True))
    print(f"{resets} resets")
    assert resets >= 5  # partial resets were compared, not only steps


def test_any_mode_steps_one_cycle_and_ignores_other_fields_actions() -> None:
    env = KeepawayEnv(6, seed=8, sync="any", **EXACT)
    td = env.reset()
    assert not td[keys.DECIDING].any()  # nobody has the ball at the start
    gen = torch.Generator().manual_seed(1)
    saw_partial = False
    for _ in range(60):
        deciding = td[keys.DECIDING].clone()
        td.set(keys.ACTION, torch.randint(0, 3, (6,), generator=gen))
        twin = KeepawayEnv(6, seed=8, sync="any", **EXACT)
        twin.sim.state, twin.sim.generator = env.sim.state.clone(), _copy_generator(env.sim.generator)
        twin._done, twin._outputs = env._done.clone(), {k: v.clone() for k, v in env._outputs.items()}
        other = td.clone().set(keys.ACTION, torch.where(deciding, td[keys.ACTION], (td[keys.ACTION] + 1) % 3))
        out, twin_out = env.step(td)["next"], twin.step(other)["next"]
        assert torch.equal(out[keys.OBSERVATION], twin_out[keys.OBSERVATION])  # other fields' actions unread
        alive = ~out[keys.DONE].view(-1)
        assert bool((out[keys.STEP_CYCLES][alive] == out[keys.STEP_CYCLES][alive].max()).all())
        assert bool((out[keys.REWARD].view(-1)[alive & ~out[keys.DECIDING]] == 0).all())
        saw_partial |= bool(out[keys.DECIDING].any() & ~out[keys.DECIDING][alive].all())
        if out[keys.DONE].any():
            out = env.reset(out.clone().set(keys.RESET, out[keys.DONE].clone()))
        td = out
    assert saw_partial


def _copy_generator(generator: torch.Generator) -> torch.Generator:
    copy = torch.Generator(device=generator.device)
    copy.set_state(generator.get_state())
    return copy


def _first_episodes(sync: str, fields: int) -> tuple[list[list[tuple]], list[tuple[int, int]]]:
    """Each field's decisions (keeper, cycle, state variables) and (duration, cause) of its first
    episode, Hand-coded keepers, no movement noise (on the compiled cycle: the env's sync is under test)."""
    env = KeepawayEnv(fields, seed=3, sync=sync, movement_noise=False, kernels="cycle", **EXACT)
    td = env.reset()
    decisions: list[list[tuple]] = [[] for _ in range(fields)]
    ends: list[tuple[int, int] | None] = [None] * fields
    while not all(ends):
        for b in td[keys.DECIDING].nonzero().flatten().tolist():
            obs = tuple(td[keys.OBSERVATION][b].tolist())
            decisions[b].append((int(td[keys.KEEPER][b]), int(td[keys.EPISODE_CYCLES][b]), obs))
        td.set(keys.ACTION, hand_coded_actions(td[keys.OBSERVATION], 3, 2))
        td = env.step(td)["next"]
        for b in td[keys.DONE].view(-1).nonzero().flatten().tolist():
            if ends[b] is None:
                ends[b] = (int(td[keys.EPISODE_CYCLES][b]), int(td[keys.END_CAUSE][b]))
    return decisions, ends


def test_any_mode_plays_the_same_episodes_as_all_mode() -> None:
    """Without movement noise the episodes after the first reset are fixed by the seed: both modes
    must give every field the same decisions and the same episode, cycle for cycle."""
    all_decisions, all_ends = _first_episodes("all", 6)
    any_decisions, any_ends = _first_episodes("any", 6)
    assert any_ends == all_ends
    assert any_decisions == all_decisions
    assert len({d for d, _ in all_ends}) > 3


def _durations(sync: str, fields: int, per_field: int) -> torch.Tensor:
    """The first ``per_field`` episode durations (cycles) of every field, Random keepers."""
    env = KeepawayEnv(fields, seed=4, sync=sync, kernels="cycle", **EXACT)
    choose = make_benchmark_policy("random", 3, 2, torch.Generator().manual_seed(4))
    td = env.reset()
    count = torch.zeros(fields, dtype=torch.long)
    kept: list[float] = []
    while int(count.min()) < per_field:
        td.set(keys.ACTION, choose(td[keys.OBSERVATION]))
        td, td_next = env.step_and_maybe_reset(td)
        done = td["next", keys.DONE].view(-1)
        kept += td["next", keys.EPISODE_CYCLES][done & (count < per_field)].tolist()
        count += done.long()
        td = td_next
    return torch.tensor(kept, dtype=torch.float64)


def test_any_mode_episode_durations_match_all_mode() -> None:
    """With movement noise the simulator's one generator is drawn in a different order, so the
    episodes differ: their durations must agree in distribution (means within 4 standard errors,
    and the spreads within 30 %)."""
    a, b = _durations("all", 48, 2), _durations("any", 48, 2)  # on the compiled cycle: the env's sync alone
    assert a.numel() == b.numel() == 96
    z = (a.mean() - b.mean()) / (a.var() / a.numel() + b.var() / b.numel()).sqrt()
    assert abs(float(z)) < 4.0, (float(a.mean()), float(b.mean()))
    assert 0.7 < float(a.std() / b.std()) < 1.3


def _episode(seed: int) -> list[tuple[int, float, int]]:
    env = KeepawayEnv(1, seed=seed, **EXACT)
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


@pytest.mark.parametrize(
    "sync,steps,options",
    [
        ("all", 30, EXACT),
        ("any", 200, EXACT),
        ("any", 150, {**EXACT, "perception": "server"}),
        ("all", 30, {"kernels": "cycle", **EXACT}),
        ("any", 300, {**EXACT, "perception": "server", "kernels": "cycle"}),
        ("any", 150, {**EXACT, "perception": "server", "kernels": "cycle", "cycle_by_cycle": True}),
    ],
)
def test_rewards_count_cycles_per_keeper(sync: str, steps: int, options: dict) -> None:
    """Deciding fields get cycles since that keeper's last decision, ended fields the end rewards,
    other fields 0; so each keeper's rewards add up to the episode's length after its first decision
    (with the "cycle" decision timing; the "server" one restarts the clock while a pass carries on)."""
    env = KeepawayEnv(4, seed=3, sync=sync, **options)
    td = env.reset()
    last: dict[int, dict[int, int]] = {b: {} for b in range(4)}  # field -> keeper -> cycle of last decision
    first: dict[int, dict[int, int]] = {b: {} for b in range(4)}
    total: dict[int, dict[int, float]] = {b: {} for b in range(4)}  # rewards received after the first

    def note_decisions(td) -> None:
        for b in td[keys.DECIDING].nonzero().flatten().tolist():
            k, cycles = int(td[keys.KEEPER][b]), int(td[keys.EPISODE_CYCLES][b])
            first[b].setdefault(k, cycles)
            total[b].setdefault(k, 0.0)
            last[b][k] = cycles

    note_decisions(td)
    checked = ended = idle = 0
    gen = torch.Generator().manual_seed(0)
    for _ in range(steps):
        td.set(keys.ACTION, torch.randint(0, 3, (4,), generator=gen))
        out = env.step(td)["next"]
        for b in range(4):
            cycles = int(out[keys.EPISODE_CYCLES][b])
            reward = out[keys.REWARD][b].item()
            if bool(out[keys.DONE][b]):
                end_rewards = out[EPISODE_END_REWARDS][b]
                for k in range(3):
                    assert end_rewards[k].item() == (cycles - last[b][k] if k in last[b] else 0)
                    if k in first[b]:
                        assert total[b][k] + end_rewards[k].item() == cycles - first[b][k]
                assert reward == cycles - max(last[b].values())
                assert out[keys.END_CAUSE][b].item() in (1, 2)
                assert not out[keys.DECIDING][b].item()
                ended += 1
            elif bool(out[keys.DECIDING][b]):
                k = int(out[keys.KEEPER][b])
                assert reward == cycles - last[b].get(k, cycles)
                total[b][k] = total[b].get(k, 0.0) + reward
                checked += 1
            else:
                assert reward == 0.0
                idle += 1
        note_decisions(out)
        if out[keys.DONE].any():
            done = out[keys.DONE].clone()
            out = env.reset(out.clone().set(keys.RESET, done))
            for b in done.squeeze(-1).nonzero().flatten().tolist():
                last[b], first[b], total[b] = {}, {}, {}
            note_decisions(out)
        td = out
    assert checked > 20 and ended >= (1 if sync == "all" else 4)
    assert (idle > 0) == (sync == "any")


@pytest.mark.parametrize("sync", SYNCS)
def test_cycle_by_cycle_shows_a_hook_on_the_simulators_step_every_cycle(sync: str) -> None:
    """The browser trainer's view on the whole-cycle kernels: each simulated cycle is one call of
    ``sim.step`` (one compiled cycle), so a hook there sees every cycle the steps and resets count."""
    env = KeepawayEnv(2, seed=5, sync=sync, kernels="cycle", cycle_by_cycle=True, decision_period_cycles=5)
    assert env.sim.compiled is not None and not env.whole_steps
    calls, step = [0], env.sim.step

    def counted(*args, **kwargs):
        calls[0] += 1
        return step(*args, **kwargs)

    env.sim.step = counted
    td = env.reset()
    at_reset = calls[0]
    assert (at_reset > 0) == (sync == "all")  # "all" runs each field to its first decision in reset
    gen, cycles, ended = torch.Generator().manual_seed(0), 0, 0
    for _ in range(60):
        td[keys.ACTION] = torch.randint(0, 3, (2,), generator=gen)
        before = calls[0]
        out, td = env.step_and_maybe_reset(td)
        stepped = int(out["next", keys.STEP_CYCLES].max())  # the fields run in lock-step within a step
        ended += int(out["next", keys.DONE].sum())
        assert stepped >= 1
        # "any" resets run no cycle; "all" ones run a restarted field to its first decision
        assert calls[0] - before == stepped if sync == "any" else calls[0] - before >= stepped
        cycles += stepped
    assert cycles >= 60 and ended >= 1


def test_decision_period_makes_holds_last_five_cycles() -> None:
    env = KeepawayEnv(4, seed=4, decision_period_cycles=5, **EXACT)
    td = env.reset()
    td.set(keys.ACTION, torch.zeros(4, dtype=torch.long))
    out = env.step(td)["next"]
    same_keeper = out[keys.KEEPER] == td[keys.KEEPER]
    alive = ~out[keys.DONE].squeeze(-1)
    assert (out["step_cycles"][same_keeper & alive] >= 5).all()


def test_gym_registration_is_idempotent_and_env_runs() -> None:
    register_keepaway()
    register_keepaway()
    env = gymnasium.make(ENV_ID, render_mode="rgb_array", keepers=4, takers=3, **EXACT)
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
    sim = KeepawaySimulator(2, KeepawayConfig(keepers=5, takers=4, **EXACT), seed=0)
    frame = render_rgb(sim.state, 1, sim.config)
    assert frame.shape[2] == 3 and frame.dtype == np.uint8
    assert (frame == np.array([220, 40, 40], dtype=np.uint8)).all(-1).any()  # takers drawn
    path = write_gif([frame, render_rgb(sim.state, 0, sim.config)], tmp_path / "ep.gif")
    assert path.stat().st_size > 0


def test_benchmark_runner_fields() -> None:
    result = play_benchmark_policy("hold", 12, batch=6, progress=False, **EXACT)
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
    result = play_benchmark_policy(
        "random", 8, keepers=keepers, takers=takers, batch=8, progress=False, **EXACT
    )
    assert result["episodes"] == 8 and result["mean_s"] > 0.5


@pytest.mark.parametrize("preset", ["2005", "rcss19"])
def test_always_hold_episodes_are_taken_within_a_bounded_time(preset: str) -> None:
    """Always Hold against the takers must end, mostly by a turnover, within seconds (the
    reference HoldBall side rule froze it in a turn-only cycle, docs/keepaway.md item 14)."""
    sim = KeepawaySimulator(64, KeepawayConfig(preset=preset, **EXACT), seed=7)
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
