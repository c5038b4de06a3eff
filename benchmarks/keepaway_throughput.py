"""Simulated keepaway field-cycles per second on one CPU thread (and on the GPU if present).

Runs the batched simulator with the Hand-coded keepers deciding inside each cycle (the
benchmark-policy path) and, separately, the TorchRL env (SMDP steps, fields waiting for the
slowest one), for B = 1, 64, 1024, 8192. On CPU the simulator runs three ways, side by side: with
the per-search numba kernels (the default there), with the pure-torch path as the reference, and
with whole cycles compiled (``kernels=cycle``: the hand-coded keepers decide inside the compiled
loop, ``KeepawaySimulator.play_policy``). Prints one JSON object, per thread count of
``--threads`` (torch's and numba's; the whole-cycle kernels split the fields over the threads).
``--perception server`` (with
the reference HoldBall rule and decision timing, the domain config's defaults) times every player
acting on its own world model; ``exact`` the true state.

    python benchmarks/keepaway_throughput.py [--cycles 40] [--repeats 5] [--batches 1 64 1024 8192]
        [--perception exact|server]

``--env-steps-only`` times just ``KeepawayEnv.step_and_maybe_reset`` (what the Sarsa loop calls) with
pre-drawn random actions, so the policy costs nothing: env steps (one per field) per second for each
``--env-syncs`` mode and ``--env-batches`` size, on the whole-cycle path and, side by side, the default
CPU path (fewer steps: it is slower by orders of magnitude) and the whole-cycle kernel one cycle per
call (``cycle_by_cycle``: the browser trainer's run, whose page is drawn after every cycle).

    python benchmarks/keepaway_throughput.py --env-steps-only [--env-batches 1 10 1024]
        [--env-syncs all any] [--env-seconds 3]
"""

from __future__ import annotations

import argparse
import json
import time

import numba
import torch

torch.set_num_threads(1)

from hfrl_torch import keys  # noqa: E402
from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawayEnv, KeepawaySimulator, hand_coded_actions  # noqa: E402


def task(preset: str, perception: str) -> dict[str, str]:
    """The simulator options of ``perception`` (``TASKS``: server perception with the reference's
    HoldBall rule and decision timing, the domain config's defaults, or the exact state with the spec's)."""
    return {"preset": preset, **TASKS[perception]}


def simulator_rates(
    batch: int,
    cycles: int,
    device: str,
    preset: str,
    kernels: list[str],
    repeats: int = 1,
    perception: str = "exact",
) -> dict[str, float]:
    """Field-cycles per second of the simulator with the hand-coded policy inline, for each
    kernel choice. The choices' timed runs of ``cycles`` cycles alternate (an A/B run in one
    process, so the VM's drifting speed hits them alike) and the best of ``repeats`` counts."""
    sims = {
        k: KeepawaySimulator(
            batch, KeepawayConfig(kernels=k, **task(preset, perception)), device=device, seed=0
        )
        for k in kernels
    }

    def one_cycle(sim: KeepawaySimulator) -> None:
        obs, _ = sim.observe(sim.decision().holder)
        sim.step(hand_coded_actions(obs, sim.config.keepers, sim.config.takers), auto_reset=True)

    def run(sim: KeepawaySimulator) -> None:
        if sim.kernels == "cycle":  # every field plays ``cycles`` cycles in one compiled call
            sim.play_policy("hand", episodes_per_field=cycles, max_cycles=cycles)
            return
        for _ in range(cycles):
            one_cycle(sim)

    for sim in sims.values():
        for _ in range(3):  # includes numba's compilation (or loading it from the cache)
            one_cycle(sim)
        if sim.kernels == "cycle":
            sim.play_policy("hand", episodes_per_field=3, max_cycles=3)
    best = dict.fromkeys(sims, float("inf"))
    for _ in range(repeats):
        for name, sim in sims.items():
            if device == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            run(sim)
            if device == "cuda":
                torch.cuda.synchronize()
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: batch * cycles / seconds for name, seconds in best.items()}


def env_rate(
    batch: int, steps: int, device: str, preset: str, perception: str = "exact", kernels: str = "auto"
) -> dict[str, float]:
    """Active field-cycles and SMDP steps per second of the TorchRL env (hand-coded keepers)."""
    env = KeepawayEnv(batch, device=device, seed=0, kernels=kernels, **task(preset, perception))
    td = env.reset()
    for _ in range(2):  # warm-up (compilation or loading the kernels)
        td.set(keys.ACTION, hand_coded_actions(td[keys.OBSERVATION], 3, 2))
        td = env.step(td)["next"]
        if td[keys.DONE].any():
            td = env.reset(td.clone().set(keys.RESET, td[keys.DONE].clone()))
    cycles = 0
    start = time.perf_counter()
    for _ in range(steps):
        td.set(keys.ACTION, hand_coded_actions(td[keys.OBSERVATION], 3, 2))
        out = env.step(td)["next"]
        cycles += int(out["step_cycles"].sum())
        if out[keys.DONE].any():
            out = env.reset(out.clone().set(keys.RESET, out[keys.DONE].clone()))
        td = out
    elapsed = time.perf_counter() - start
    return {"field_cycles_per_s": cycles / elapsed, "env_steps_per_s": batch * steps / elapsed}


def env_step_rate(
    batch: int, sync: str, kernels: str, seconds: float, preset: str, perception: str, by_cycle: bool = False
) -> dict[str, float]:
    """Env steps (``step_and_maybe_reset`` calls times B) and calls per second, random actions drawn
    beforehand, run for about ``seconds`` after a warm-up; with the steps that hit an episode end."""
    env = KeepawayEnv(
        batch,
        device="cpu",
        seed=0,
        sync=sync,
        kernels=kernels,
        cycle_by_cycle=by_cycle,
        **task(preset, perception),
    )
    gen = torch.Generator().manual_seed(0)
    actions = torch.randint(0, env.config.num_actions, (64, batch), generator=gen)
    td = env.reset()
    for i in range(5):  # warm-up (compilation or loading the kernels)
        td.set(keys.ACTION, actions[i % 64])
        _, td = env.step_and_maybe_reset(td)
    calls = ends = 0
    start = time.perf_counter()
    while True:
        for _ in range(16):
            td.set(keys.ACTION, actions[calls % 64])
            out, td = env.step_and_maybe_reset(td)
            ends += int(out["next", keys.DONE].any())
            calls += 1
        elapsed = time.perf_counter() - start
        if elapsed >= seconds:
            break
    return {
        "env_steps_per_s": round(batch * calls / elapsed),
        "calls_per_s": round(calls / elapsed),
        "us_per_call": round(1e6 * elapsed / calls, 1),
        "share_of_calls_with_an_end": round(ends / calls, 3),
    }


def env_steps_only(args: argparse.Namespace) -> None:
    """``--env-steps-only``: the env's own step rate per sync mode and batch size, cycle vs default path,
    and (small B) the whole-cycle kernel stepped one cycle per call, as the browser trainer's run does."""
    result: dict[str, object] = {"preset": args.preset, "perception": args.perception, "env": {}}
    for sync in args.env_syncs:
        for b in args.env_batches:
            common = (args.env_seconds, args.preset, args.perception)
            row = {"cycle": env_step_rate(b, sync, "cycle", *common)}
            if b <= args.reference_max_batch:
                row["cycle_by_cycle"] = env_step_rate(b, sync, "cycle", *common, by_cycle=True)
                row["auto"] = env_step_rate(b, sync, "auto", *common)
            result["env"][f"sync={sync} B={b}"] = row
    print(json.dumps(result, indent=2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=40)
    parser.add_argument("--env-steps", type=int, default=20)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 8192])
    parser.add_argument("--preset", default="2005")
    parser.add_argument("--repeats", type=int, default=1, help="timed simulator runs; the best is reported")
    parser.add_argument("--devices", nargs="+", help="default: cpu, and cuda when present")
    parser.add_argument("--perception", default="exact", choices=("exact", "server"))
    parser.add_argument("--threads", type=int, nargs="+", default=[1], help="thread counts to time")
    parser.add_argument(
        "--cycle-field-cycles",
        type=int,
        default=200_000,
        help="field-cycles per timed run of the whole-cycle path (at least --cycles cycles)",
    )
    parser.add_argument("--no-env", action="store_true", help="skip the TorchRL env")
    parser.add_argument("--env-steps-only", action="store_true", help="time only env steps (see above)")
    parser.add_argument("--env-batches", type=int, nargs="+", default=[1, 10, 1024])
    parser.add_argument("--env-syncs", nargs="+", default=["all", "any"], choices=("all", "any"))
    parser.add_argument("--env-seconds", type=float, default=3.0, help="timed seconds per env measurement")
    parser.add_argument(
        "--reference-max-batch", type=int, default=10, help="largest B timed on the default path"
    )
    args = parser.parse_args()
    if args.env_steps_only:
        numba.set_num_threads(1)
        env_steps_only(args)
        return
    devices = args.devices or ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    result: dict[str, object] = {
        "preset": args.preset,
        "perception": args.perception,
        "cycles": args.cycles,
        "cycle_kernel_field_cycles": args.cycle_field_cycles,
        "runs": {},
    }
    for threads in args.threads:
        numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
        torch.set_num_threads(threads)
        run: dict[str, object] = {"simulator": {}, "env": {}}
        for device in devices:
            kernels = ["numba", "torch", "cycle"] if device == "cpu" else ["torch"]
            rates = {}
            for b in args.batches:
                rates[b] = simulator_rates(
                    b,
                    args.cycles,
                    device,
                    args.preset,
                    [k for k in kernels if k != "cycle"],
                    args.repeats,
                    args.perception,
                )
                if "cycle" in kernels:
                    rates[b].update(
                        simulator_rates(
                            b,
                            max(args.cycles, args.cycle_field_cycles // b),
                            device,
                            args.preset,
                            ["cycle"],
                            args.repeats,
                            args.perception,
                        )
                    )
            run["simulator"][device] = {
                k: {str(b): round(rates[b][k]) for b in args.batches} for k in kernels
            }
            if not args.no_env:
                run["env"][device] = {
                    f"{b} {k}": {
                        name: round(v)
                        for name, v in env_rate(
                            b,
                            args.env_steps * (50 if k == "cycle" else 1),
                            device,
                            args.preset,
                            args.perception,
                            k,
                        ).items()
                    }
                    for b in args.batches
                    if b <= 1024
                    for k in (["auto", "cycle"] if device == "cpu" else ["auto"])
                }
        result["runs"][str(threads)] = run
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
