"""Simulated keepaway field-cycles per second on one CPU thread (and on the GPU if present).

Runs the batched simulator with the Hand-coded keepers deciding inside each cycle (the
benchmark-policy path) and, separately, the TorchRL env (SMDP steps, fields waiting for the
slowest one), for B = 1, 64, 1024, 8192. Prints one JSON object.

    python benchmarks/keepaway_throughput.py [--cycles 40] [--repeats 5] [--batches 1 64 1024 8192]
"""

from __future__ import annotations

import argparse
import json
import time

import torch

torch.set_num_threads(1)

from hfrl_torch import keys  # noqa: E402
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv, KeepawaySimulator, hand_coded_actions  # noqa: E402


def simulator_rate(batch: int, cycles: int, device: str, preset: str, repeats: int = 1) -> float:
    """Field-cycles per second of the simulator with the hand-coded policy inline (the best of
    ``repeats`` timed runs of ``cycles`` cycles, which filters out a noisy machine's slow spells)."""
    config = KeepawayConfig(preset=preset)
    sim = KeepawaySimulator(batch, config, device=device, seed=0)

    def one_cycle() -> None:
        obs, _ = sim.observe(sim.decision().holder)
        sim.step(hand_coded_actions(obs, config.keepers, config.takers), auto_reset=True)

    for _ in range(3):
        one_cycle()
    best = float("inf")
    for _ in range(repeats):
        if device == "cuda":
            torch.cuda.synchronize()
        start = time.perf_counter()
        for _ in range(cycles):
            one_cycle()
        if device == "cuda":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - start)
    return batch * cycles / best


def env_rate(batch: int, steps: int, device: str, preset: str) -> dict[str, float]:
    """Active field-cycles and SMDP steps per second of the TorchRL env (hand-coded keepers)."""
    env = KeepawayEnv(batch, device=device, seed=0, preset=preset)
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
    args = parser.parse_args()
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    result: dict[str, object] = {
        "threads": torch.get_num_threads(),
        "preset": args.preset,
        "simulator": {},
        "env": {},
    }
    for device in devices:
        result["simulator"][device] = {
            str(b): round(simulator_rate(b, args.cycles, device, args.preset, args.repeats))
            for b in args.batches
        }
        result["env"][device] = {
            str(b): {k: round(v) for k, v in env_rate(b, args.env_steps, device, args.preset).items()}
            for b in args.batches
            if b <= 1024
        }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
