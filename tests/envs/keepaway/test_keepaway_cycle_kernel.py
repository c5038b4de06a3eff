"""Whole cycles in compiled code (``kernels="cycle"``) against the torch path: one cycle at a time
from the same state and draws (within float32 rounding, apart from near-ties; see the budget
below), the SMDP advance, the benchmark policies' statistics, and the choice of path."""

from __future__ import annotations

import dataclasses
import math

import numba
import numpy as np
import pytest
import torch

from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawaySimulator, hand_coded_actions
from hfrl_torch.envs.keepaway.benchmark_policies import play_benchmark_policy
from hfrl_torch.envs.keepaway.params import resolve_kernels
from hfrl_torch.envs.keepaway.simulator import KeepawayState

SERVER = TASKS["server"]
EXACT = TASKS["exact"]
TOLERANCE = 1e-3  # metres, m/cycle, radians: float32 rounding after one cycle is ~1e-6


def field_mismatch(a: KeepawaySimulator, b: KeepawaySimulator) -> torch.Tensor:
    """Fields [B] whose state differs between the two simulators beyond rounding (angles mod 2 pi)."""
    bad = torch.zeros(a.batch_size, dtype=torch.bool)
    for name, x in a.state.tensors().items():
        y = getattr(b.state, name)
        if x.numel() == 0:
            continue
        if x.dtype.is_floating_point:
            d = (x - y).abs().reshape(a.batch_size, -1)
            if name.endswith("body"):
                d = torch.minimum(d, 2 * math.pi - d)
            bad |= (d > TOLERANCE).any(1)
        else:
            bad |= (x != y).reshape(a.batch_size, -1).any(1)
    return bad


def compare_cycles(config: KeepawayConfig, fields: int, cycles: int, scramble: bool = False) -> float:
    """Share of field-cycles on which one compiled cycle and one torch cycle from the same state
    and the same uniforms disagree; the states are re-synchronised every cycle."""
    torch_sim = KeepawaySimulator(fields, config.replace(kernels="torch"), seed=11)
    cycle_sim = KeepawaySimulator(fields, config.replace(kernels="cycle"), seed=11)
    g = torch.Generator().manual_seed(3)
    bad = 0
    for c in range(cycles):
        if scramble and c % 10 == 0:
            torch_sim.state = scrambled(torch_sim.state, g)
        obs, _ = torch_sim.observe(torch_sim.decision().holder)
        actions = hand_coded_actions(obs, config.keepers, config.takers)
        if c % 3 == 1:  # random passes too
            actions = torch.randint(0, config.keepers, (fields,), generator=g)
        cycle_sim.state = torch_sim.state.clone()
        cycle_sim.generator.set_state(torch_sim.generator.get_state())
        out_t = torch_sim.step(actions)
        out_c = cycle_sim.step(actions)
        mismatch = field_mismatch(torch_sim, cycle_sim) | (out_t.end_cause != out_c.end_cause)
        bad += int(mismatch.sum())
        torch_sim.reset(out_t.ended)
    return bad / (fields * cycles)


def scrambled(state: KeepawayState, g: torch.Generator) -> KeepawayState:
    """A random scene: positions anywhere near the ball, fast balls, random headings and macro-actions
    (beliefs move with the truth so that the world models stay plausible)."""
    b, o = state.pos.shape[:2]
    ball = state.pos[:, :1]
    pos = ball + (torch.rand(b, o, 2, generator=g) * 2 - 1) * 3.0
    pos[:, 0] = ball[:, 0]
    vel = (torch.rand(b, o, 2, generator=g) * 2 - 1) * 0.5
    vel[:, 0] *= 4.0
    body = (torch.rand(b, o, generator=g) * 2 - 1) * math.pi
    shift_pos = (pos - state.pos).unsqueeze(1)
    n = state.keepers
    pass_target = torch.randint(-1, n, (b,), generator=g)
    return dataclasses.replace(
        state,
        pos=pos,
        vel=vel,
        body=body,
        seen_pos=state.seen_pos + shift_pos if state.seen_pos.numel() else state.seen_pos,
        seen_vel=vel.unsqueeze(1).expand_as(state.seen_vel) if state.seen_vel.numel() else state.seen_vel,
        pass_target=pass_target,
        prev_holder=torch.randint(-1, n, (b,), generator=g),
    ).clone()


@pytest.mark.parametrize("preset", ["2005", "rcss19"])
def test_exact_cycles_agree(preset: str) -> None:
    """Exact perception: nearly every field-cycle agrees with torch within rounding."""
    assert compare_cycles(KeepawayConfig(preset=preset, **EXACT), 48, 60) <= 0.005


@pytest.mark.parametrize(
    "options",
    [
        {"preset": "2005", **SERVER},
        {"preset": "rcss19", **SERVER},
        {"keepers": 4, "takers": 3, **SERVER},
        {"keepers": 4, "takers": 3, "noisy_observations": True, **EXACT},
        {"decision_period_cycles": 5, **SERVER},
    ],
)
def test_server_perception_cycles_agree(options: dict) -> None:
    """Server perception: the quantised sightings put distances on exact multiples of 0.1 m, so
    distance ties (teammate order, GoToBall's 10 m and 20 m steps) and the sign of a frozen ball's
    believed velocity (the opponents' drift) are decided by rounding on either path; ~1 % of the
    field-cycles, and the rest agrees within rounding."""
    assert compare_cycles(KeepawayConfig(**options), 32, 45, scramble=True) <= 0.03


def test_scrambled_exact_scenes_agree() -> None:
    """Random scenes (crowded, fast balls, random macro-actions) under exact perception."""
    assert compare_cycles(KeepawayConfig(**EXACT), 48, 40, scramble=True) <= 0.01


@pytest.mark.parametrize("policy", ["hold", "random"])
def test_benchmark_statistics_agree(policy: str) -> None:
    """The benchmark policies' mean episode length on the compiled path lies within the torch
    path's interval (both with 120 episodes on the default task). The reference runs on the per-skill
    numba kernels, which play the torch path bit for bit (test_keepaway_kernels'
    test_simulated_episodes_identical) in two thirds of its time."""
    ref = play_benchmark_policy(policy, 120, batch=60, progress=False, kernels="numba", **SERVER)
    sim = KeepawaySimulator(60, KeepawayConfig(kernels="cycle", **SERVER), seed=0)
    durations, causes, played, _ = sim.play_policy(policy, 2)
    assert bool((played == 2).all())
    seconds = durations.reshape(-1).double() / 10.0
    mean, se = float(seconds.mean()), float(seconds.std() / math.sqrt(seconds.numel()))
    ref_se = (ref["ci95_high"] - ref["ci95_low"]) / (2 * 1.96)
    assert abs(mean - ref["mean_s"]) < 3.0 * math.hypot(se, ref_se)
    taken = float((causes == 2).double().mean())
    assert abs(taken - ref["taken_share"]) < 0.15


def test_a_pass_goes_to_the_teammate_observe_numbers() -> None:
    """``step`` on the compiled cycle sends PassBall k to the k-th teammate of ``observe``'s order: under
    server perception two teammates often lie at the same seen distance, and the torch ordering broke such
    ties otherwise than the compiled cycle (evaluate.py's Hand-coded lost 2 s an episode, rcss19)."""
    sim = KeepawaySimulator(200, KeepawayConfig(kernels="cycle", preset="rcss19", **SERVER), seed=5)
    g = torch.Generator().manual_seed(0)
    checked = 0
    for _ in range(150):
        dec = sim.decision()
        _, order = sim.observe(dec.holder)
        actions = torch.randint(1, 3, (200,), generator=g)
        sim.step(actions, auto_reset=True)
        passed = dec.must_decide & (sim.state.episode_cycles > 0)
        wanted = order.gather(1, (actions - 1).unsqueeze(-1)).squeeze(-1)
        assert bool((sim.state.pass_target[passed] == wanted[passed]).all())
        checked += int(passed.sum())
    assert checked > 1000


def test_stepping_plays_the_benchmark_policies_as_the_compiled_loop() -> None:
    """Hand-coded keepers chosen in Python each cycle (``play_benchmark_policy``, what evaluate.py runs)
    play as the ones deciding inside the compiled loop (``play_policy``), on the default task."""
    task = {"preset": "rcss19", **SERVER}
    stepped = play_benchmark_policy("hand", 600, batch=200, progress=False, kernels="cycle", **task)
    sim = KeepawaySimulator(200, KeepawayConfig(kernels="cycle", **task), seed=0)
    durations, _, played, _ = sim.play_policy("hand", 3)
    assert bool((played == 3).all())
    seconds = durations.reshape(-1).double() / 10.0
    se = float(seconds.std() / math.sqrt(seconds.numel()))
    stepped_se = (stepped["ci95_high"] - stepped["ci95_low"]) / (2 * 1.96)
    assert abs(float(seconds.mean()) - stepped["mean_s"]) < 3.0 * math.hypot(se, stepped_se)


def test_advance_runs_each_field_to_its_decision() -> None:
    """``advance``: every running field stops where its holder must decide or its episode ended,
    counting its cycles; with ``restart`` no episode is left ended."""
    sim = KeepawaySimulator(16, KeepawayConfig(kernels="cycle", **SERVER), seed=2)
    running = torch.ones(16, dtype=torch.bool)
    start = sim.state.episode_cycles.clone()
    out = sim.advance(None, running, first=False)
    dec = sim.decision()
    ended = out.cause != 0
    assert bool((dec.must_decide | ended).all())
    assert bool((out.cycles[~ended] == (sim.state.episode_cycles - start)[~ended]).all())
    actions = torch.ones(16, dtype=torch.long)
    out = sim.advance(actions, ~ended, first=True, restart=True)
    assert bool((out.cause == 0).all()) and bool((out.cycles[~ended] >= 1).all())
    assert bool(sim.decision().must_decide[~ended].all())
    any_out = sim.advance(actions, running, sync="any")
    assert int(any_out.cycles.max()) >= 1


def test_compiled_decisions_match_torch() -> None:
    """The compiled decision and state variables equal the torch ones within rounding (exact
    perception: server perception's quantised distances tie, see above)."""
    sim = KeepawaySimulator(32, KeepawayConfig(kernels="cycle", **EXACT), seed=4)
    sim.advance(None, torch.ones(32, dtype=torch.bool), first=False, restart=True)
    sim.advance(torch.zeros(32, dtype=torch.long), torch.ones(32, dtype=torch.bool), restart=True)
    holder, _, must, obs = sim.compiled.decisions(sim.state)
    ref = sim.decision()
    ref_obs, _ = sim.observe(ref.holder)
    assert torch.equal(holder, ref.holder) and torch.equal(must, ref.must_decide)
    assert torch.allclose(obs, ref_obs, atol=1e-4)


def test_kernel_choice_and_errors() -> None:
    """``cycle`` is a valid ``kernels`` value for float32 on CPU only; the compiled-only calls say so."""
    assert resolve_kernels("cycle", torch.device("cpu")) == "cycle"
    with pytest.raises(ValueError, match="kernels='cycle' runs float32 on the CPU only"):
        KeepawaySimulator(2, KeepawayConfig(kernels="cycle", **EXACT), dtype=torch.float64)
    with pytest.raises(ValueError, match="kernels='bogus' is invalid; allowed: auto, numba, torch, cycle"):
        KeepawayConfig(kernels="bogus")
    with pytest.raises(ValueError, match="needs kernels='cycle', not kernels='torch'"):
        KeepawaySimulator(2, KeepawayConfig(kernels="torch", **EXACT)).advance(
            None, torch.ones(2, dtype=torch.bool)
        )
    sim = KeepawaySimulator(2, KeepawayConfig(kernels="cycle", **EXACT))
    with pytest.raises(ValueError, match="policy='best' is invalid"):
        sim.play_policy("best", 1)


def test_play_is_deterministic_and_independent_of_threads() -> None:
    """A seed fixes the compiled play, whatever the number of threads the fields are split over."""
    before = numba.get_num_threads()
    results = []
    try:
        for threads in (1, min(2, numba.config.NUMBA_NUM_THREADS)):
            numba.set_num_threads(threads)
            sim = KeepawaySimulator(160, KeepawayConfig(kernels="cycle", **SERVER), seed=9)
            results.append(sim.play_policy("hand", 2))
    finally:
        numba.set_num_threads(before)
    assert torch.equal(results[0][0], results[1][0]) and torch.equal(results[0][1], results[1][1])


def test_the_interception_shortcuts_keep_the_fastest_keeper_and_its_point() -> None:
    """``_keeper_intercepts`` searches a keeper only below the fastest before it (and only the
    holder's when the ball is kickable): the fastest keeper, its cycles and its point are those of
    the full search, on random views (the commands read nothing else)."""
    from hfrl_torch.envs.keepaway.compiled.common import NO_CAP, N
    from hfrl_torch.envs.keepaway.compiled.glue import task_arrays
    from hfrl_torch.envs.keepaway.compiled.keepers import _fastest, _keeper_intercepts
    from hfrl_torch.envs.keepaway.compiled.skills import _intercept

    prm, ip, tabs, _ = task_arrays(KeepawayConfig(kernels="cycle", **EXACT))
    g = torch.Generator().manual_seed(5)
    n = int(ip[N])
    for trial in range(400):
        vpos = (torch.rand(6, 2, generator=g) * 20 - 10).numpy().astype("float32")
        vvel = ((torch.rand(6, 2, generator=g) * 2 - 1) * (0.2 + trial % 5 / 4)).numpy().astype("float32")
        vbody = ((torch.rand(6, generator=g) * 2 - 1) * math.pi).numpy().astype("float32")
        holder, kickable = trial % n, bool(trial % 3 == 0)
        full = [_intercept.py_func(1 + k, vpos, vvel, vbody, prm, ip, tabs, NO_CAP) for k in range(n)]
        icyc, ipts = np.empty(n, dtype=np.int64), np.empty((n, 2))
        _keeper_intercepts.py_func(vpos, vvel, vbody, holder, kickable, prm, ip, tabs, icyc, ipts)
        want = _fastest.py_func(np.array([c for c, _, _ in full], dtype=np.int64), holder, kickable)
        got = _fastest.py_func(icyc, holder, kickable)
        assert got == want
        assert icyc[got] == full[got][0]
        if not kickable:
            assert tuple(ipts[got]) == full[got][1:]


def test_the_quantisation_tables_give_the_direct_computation_bits() -> None:
    """The sensor's distance and direction tables (compiled lookups in ``_observe``) hold exactly
    what the direct formulas compute in compiled code."""
    from hfrl_torch.envs.keepaway.compiled import perception as K
    from hfrl_torch.envs.keepaway.compiled.common import DEG

    @numba.njit
    def direct(d: float, k: int) -> tuple[float, float, float]:
        qdist = np.rint(np.exp(np.rint(np.log(d + 1e-10) / 0.1) * 0.1) / 0.1) * 0.1
        return qdist, np.cos(np.float64(k) * DEG), np.sin(np.float64(k) * DEG)

    for i, d in enumerate(np.concatenate([[0.0, 1e-9, 0.05, 1e6], np.geomspace(0.01, 150.0, 2000)])):
        k = i % 361 - 180
        qdist, cos, sin = direct(d, k)
        assert K._qdist(d) == qdist
        assert (K.COS_DEG[k + 180], K.SIN_DEG[k + 180]) == (cos, sin)
