"""Simulated keepaway field-cycles per second on one CPU thread (and on the GPU if present).

Runs the batched simulator with the Hand-coded keepers deciding inside each cycle (the
benchmark-policy path) and, separately, the TorchRL env (SMDP steps, fields waiting for the
slowest one), for B = 1, 64, 1024, 8192. On CPU the simulator runs twice, side by side: with the
numba kernels (the default there) and with the pure-torch path as the reference. Prints one
JSON object. One torch thread; the numba kernels are serial loops. ``--perception server`` (with
the reference HoldBall rule and decision timing, the domain config's defaults) times every player
acting on its own world model; ``exact`` the true state.

    python benchmarks/keepaway_throughput.py [--cycles 40] [--repeats 5] [--batches 1 64 1024 8192]
        [--perception exact|server]
"""

from __future__ import annotations

import argparse
import json
import time

import torch

torch.set_num_threads(1)

from hfrl_torch import keys  # noqa: E402
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv, KeepawaySimulator, hand_coded_actions  # noqa: E402


def task(preset: str, perception: str) -> dict[str, str]:
    """The simulator options of ``perception``: server perception with the reference's HoldBall
    rule and decision timing (the domain config's defaults), or the exact state with the spec's."""
    if perception == "server":
        return {
            "preset": preset,
            "perception": "server",
            "hold_ball": "reference",
            "decision_timing": "server",
        }
    return {"preset": preset, "perception": "exact", "hold_ball": "spec", "decision_timing": "cycle"}


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

    for sim in sims.values():
        for _ in range(3):  # includes numba's compilation (or loading it from the cache)
            one_cycle(sim)
    best = dict.fromkeys(sims, float("inf"))
    for _ in range(repeats):
        for name, sim in sims.items():
            if device == "cuda":
                torch.cuda.synchronize()
            start = time.perf_counter()
            for _ in range(cycles):
                one_cycle(sim)
            if device == "cuda":
                torch.cuda.synchronize()
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: batch * cycles / seconds for name, seconds in best.items()}


def env_rate(batch: int, steps: int, device: str, preset: str, perception: str = "exact") -> dict[str, float]:
    """Active field-cycles and SMDP steps per second of the TorchRL env (hand-coded keepers)."""
    env = KeepawayEnv(batch, device=device, seed=0, **task(preset, perception))
    td = env.reset()
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=40)
    parser.add_argument("--env-steps", type=int, default=20)
    parser.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 8192])
    parser.add_argument("--preset", default="2005")
    parser.add_argument("--repeats", type=int, default=1, help="timed simulator runs; the best is reported")
    parser.add_argument("--devices", nargs="+", help="default: cpu, and cuda when present")
    parser.add_argument("--perception", default="exact", choices=("exact", "server"))
    args = parser.parse_args()
    devices = args.devices or ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    result: dict[str, object] = {
        "threads": torch.get_num_threads(),
        "preset": args.preset,
        "perception": args.perception,
        "simulator": {},
        "env": {},
    }
    for device in devices:
        kernels = ["numba", "torch"] if device == "cpu" else ["torch"]
        rates = {
            b: simulator_rates(b, args.cycles, device, args.preset, kernels, args.repeats, args.perception)
            for b in args.batches
        }
        result["simulator"][device] = {k: {str(b): round(rates[b][k]) for b in args.batches} for k in kernels}
        result["env"][device] = {
            str(b): {
                k: round(v)
                for k, v in env_rate(b, args.env_steps, device, args.preset, args.perception).items()
            }
            for b in args.batches
            if b <= 1024
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
