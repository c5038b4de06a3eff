"""The whole-cycle path's reset (``kernels="cycle"``: per field in compiled code, from each field's own
random stream) against the torch path's ``fresh_state``, and the compiled env step's outputs."""

from __future__ import annotations

import numba
import pytest
import torch

from hfrl_torch import keys
from hfrl_torch.envs.keepaway import (
    TASKS,
    KeepawayConfig,
    KeepawayEnv,
    KeepawaySimulator,
    play_benchmark_policy,
)
from hfrl_torch.envs.keepaway.compiled.glue import MIN_FIELDS_PER_THREAD, _parts
from hfrl_torch.envs.keepaway.perception import observe

SERVER = TASKS["server"]
FIELDS = 3000
KS_LIMIT = 0.05  # two-sample Kolmogorov-Smirnov statistic; 3000 vs 3000 draws: p ~ 1e-3 at 0.05


def ks_statistic(a: torch.Tensor, b: torch.Tensor) -> float:
    """The largest gap between the empirical distribution functions of samples ``a`` and ``b``."""
    both = torch.cat((a, b)).sort().values
    fa = torch.searchsorted(a.sort().values, both, right=True).double() / a.numel()
    fb = torch.searchsorted(b.sort().values, both, right=True).double() / b.numel()
    return float((fa - fb).abs().max())


def test_compiled_reset_is_distributed_like_fresh_state() -> None:
    """Same fixed parts (ball, zero velocities, counters), positions in the region with the torch
    path's distribution per object and axis, and world models equal to a see of the new state."""
    config = KeepawayConfig(**SERVER)
    cycle = KeepawaySimulator(FIELDS, config.replace(kernels="cycle"), seed=0)
    ref = KeepawaySimulator(FIELDS, config.replace(kernels="torch"), seed=0)
    s, r = cycle.state, ref.state
    assert torch.equal(s.pos[:, 0], r.pos[:, 0])  # the ball's start
    for name in ("vel", "counter", "episode_cycles", "last_decision", "prev_holder", "pass_target"):
        assert torch.equal(getattr(s, name), getattr(r, name)), name
    assert torch.equal(s.action_start, r.action_start) and torch.equal(s.clock, r.clock)
    half = torch.tensor([config.length, config.width]) / 2
    assert bool((s.pos.abs() < half).all())
    for o in range(1, s.pos.shape[1]):
        for axis in (0, 1):
            assert ks_statistic(s.pos[:, o, axis], r.pos[:, o, axis]) < KS_LIMIT, (o, axis)
    # which corner each keeper starts in: each of the n slots about equally often on both paths
    corner = (s.pos[:, 1:4] > 0).long() @ torch.tensor([1, 2])
    shares = torch.stack([(corner == c).double().mean(0) for c in (0, 1, 3)])
    assert bool(((shares - 1 / 3).abs() < 0.04).all())
    prior_vel = torch.zeros_like(s.seen_vel)
    seen = observe(s.pos, s.vel, s.body, s.seen_pos, prior_vel, s.seen_body, config.keepers, cycle.physics)
    for mine, want in zip((s.seen_pos, s.seen_vel, s.seen_body), seen, strict=True):
        close = (mine - want).abs() <= 1e-3
        assert float(close.double().mean()) > 0.999  # the rest: quantisation ties rounded apart


def test_partial_compiled_reset_touches_only_its_fields_and_is_field_local() -> None:
    """Fields outside the mask keep their state and stream; a restarted field's new episode depends
    only on its own stream, not on the batch size or on which other fields restart."""
    config = KeepawayConfig(kernels="cycle", **SERVER)
    a = KeepawaySimulator(6, config, seed=3)
    b = KeepawaySimulator(4, config, seed=3)
    assert torch.equal(a.state.pos[:4], b.state.pos)  # the first episodes: per field too
    for sim in (a, b):
        everyone = torch.ones(sim.batch_size, dtype=torch.bool)
        sim.advance(None, everyone, first=False, restart=True)
        sim.advance(torch.ones(sim.batch_size, dtype=torch.long), everyone)
    before, streams = a.state.clone(), a.compiled.rng.copy()
    mask = torch.tensor([True, False, True, False, False, True])
    a.reset(mask)
    b.reset(torch.tensor([True, False, False, False]))
    for name, value in a.state.tensors().items():
        assert torch.equal(value[~mask], getattr(before, name)[~mask]), name
    assert (a.compiled.rng[~mask.numpy()] == streams[~mask.numpy()]).all()
    assert (a.compiled.rng[mask.numpy()] != streams[mask.numpy()]).all()
    assert bool((a.state.episode_cycles[mask] == 0).all()) and bool((a.state.vel[mask] == 0).all())
    assert torch.equal(a.state.clock, before.clock)
    for name, value in a.state.tensors().items():
        assert torch.equal(value[0], getattr(b.state, name)[0]), name


def test_compiled_env_outputs_are_the_decisions_of_the_state() -> None:
    """The compiled step's outputs: the holder's state variables and keeper on alive fields, deciding
    where the holder must decide, and done fields frozen until they are reset."""
    env = KeepawayEnv(5, seed=4, sync="any", kernels="cycle", **SERVER)
    td = env.reset()
    gen = torch.Generator().manual_seed(0)
    ended = 0
    for _ in range(120):
        td.set(keys.ACTION, torch.randint(0, 3, (5,), generator=gen))
        out = env.step(td)["next"]
        done = out[keys.DONE].squeeze(-1)
        holder, _, must, obs = env.sim.compiled.decisions(env.sim.state)
        assert torch.equal(out[keys.OBSERVATION], obs) and torch.equal(out[keys.KEEPER], holder)
        assert torch.equal(out[keys.DECIDING], must & ~done)
        assert torch.equal(out[keys.EPISODE_CYCLES], env.sim.state.episode_cycles)
        if bool(done.any()):
            ended += int(done.sum())
            frozen = out.clone()
            again = env.step(out.clone().set(keys.ACTION, torch.zeros(5, dtype=torch.long)))["next"]
            for key in (keys.OBSERVATION, keys.END_CAUSE, keys.EPISODE_END_REWARDS):
                assert torch.equal(again[key][done], frozen[key][done]), key
            assert bool((again[keys.REWARD][done] == 0).all())
            out = env.reset(again.clone().set(keys.RESET, again[keys.DONE].clone()))
        td = out
    assert ended >= 2


def test_cycle_outcomes_keep_their_episode_lengths_across_the_reset() -> None:
    """A cycle's outcome holds the ended episodes' lengths even though the compiled reset right after
    restarts those fields in place (``step(auto_reset=True)``; the benchmark runner resets after reading)."""
    sim = KeepawaySimulator(8, KeepawayConfig(kernels="cycle", **SERVER), seed=5)
    lengths = []
    for _ in range(300):
        out = sim.step(None, auto_reset=True)
        lengths += out.episode_cycles[out.ended].tolist()
        assert bool((sim.state.episode_cycles[out.ended] == 0).all())
    assert len(lengths) >= 3 and min(lengths) > 0
    result = play_benchmark_policy("hold", 6, batch=3, progress=False, kernels="cycle", **SERVER)
    assert result["median_s"] > 0.5


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs two numba threads")
@pytest.mark.parametrize("batch", [10, 256])
@pytest.mark.parametrize("sync", ["any", "all"])
def test_two_threads_step_the_env_as_one(sync: str, batch: int) -> None:
    """With two threads the whole-cycle env plays bit for bit as on one: its kernels split the fields
    over the threads (``prange`` regions), the cycle-playing ones from 8 fields, the bookkeeping from 128."""
    runs = {}
    threads_before = numba.get_num_threads()
    try:
        for threads in (1, 2):
            numba.set_num_threads(threads)
            assert _parts(batch, playing=True) == threads
            assert _parts(batch) == (threads if batch >= 2 * MIN_FIELDS_PER_THREAD else 1)
            env = KeepawayEnv(batch, KeepawayConfig(kernels="cycle", **SERVER), seed=5, sync=sync)
            gen = torch.Generator().manual_seed(1)
            td = env.reset()
            outs = []
            for _ in range(120 if sync == "any" else 25):
                td[keys.ACTION] = torch.randint(0, 3, (batch,), generator=gen)
                stepped, td = env.step_and_maybe_reset(td)
                outs.append(stepped["next"].clone())
            runs[threads] = (torch.stack(outs), env.sim.state.pos.clone())
    finally:
        numba.set_num_threads(threads_before)
    (one, pos_one), (two, pos_two) = runs[1], runs[2]
    assert bool((one[keys.DONE]).any())  # episodes ended and restarted on the way
    assert (one == two).all() and torch.equal(pos_one, pos_two)
