"""Tetris throughput: our engines and env vs tetris-gymnasium's placement wrapper, in one run.

    python benchmarks/tetris_throughput.py [--seconds 3] [--width 10 --height 20]

Prints one JSON object. Everything runs on one thread (torch and numba), the
setting of the issue's target (>= 100,000 placements/s with BT features over all
afterstates). All paths play the same fixed BT policy (few holes, flat stack),
except tetris-gymnasium, which plays uniformly random legal placements (its
wrapper computes the afterstates of all placements whatever the policy).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numba
import torch

torch.set_num_threads(1)
numba.set_num_threads(1)

from hfrl_torch import keys  # noqa: E402
from hfrl_torch.envs.tetris.engine_numba import NumbaEngine, play  # noqa: E402
from hfrl_torch.envs.tetris.env import TetrisEnv  # noqa: E402
from hfrl_torch.envs.tetris.features import BT, feature_size  # noqa: E402
from hfrl_torch.envs.tetris.pieces import placement_table  # noqa: E402
from hfrl_torch.envs.tetris.rules import TetrisRules  # noqa: E402
from hfrl_torch.models.linear import batched_values, greedy_placement  # noqa: E402


def bt_policy(width: int) -> torch.Tensor:
    """A fixed BT policy that survives long enough for resets not to matter."""
    w = torch.zeros(feature_size(BT, width), dtype=torch.float64)
    w[2 * width] = -10.0  # holes
    w[2 * width - 1] = -1.0  # max height
    w[width : 2 * width - 1] = -1.0  # |height differences|
    return w


def mean_afterstates(width: int) -> float:
    """Expected placements per piece with uniform pieces (23.1 on 10 wide)."""
    return float(placement_table(width).num_actions.mean())


def bench_fused(rules: TetrisRules, seconds: float) -> dict[str, float]:
    """Whole games in one compiled call: features of all afterstates, argmax, place (the CE inner loop)."""
    w = bt_policy(rules.width)
    play(rules, BT, w, torch.arange(2), max_pieces=50)  # compile / load the cache
    placements, t0, seed = 0, time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        _, pieces, _ = play(rules, BT, w, torch.arange(seed, seed + 4))
        placements += int(pieces.sum())
        seed += 4
    dt = time.perf_counter() - t0
    pps = placements / dt
    return {"placements_per_s": pps, "afterstates_per_s": pps * mean_afterstates(rules.width)}


def bench_engine(
    rules: TetrisRules, batch: int, seconds: float, engine: str, device: str = "cpu"
) -> dict[str, float]:
    """Batched engine calls without TorchRL: afterstates() + greedy choice + step()."""
    if engine == "numba":
        eng = NumbaEngine(rules, batch, BT)
    else:
        from hfrl_torch.envs.tetris.engine_torch import TorchEngine

        eng = TorchEngine(rules, batch, BT, device=device)
    w = bt_policy(rules.width).expand(batch, -1).to(device)
    gen = torch.Generator().manual_seed(0)
    seeds = torch.randint(0, 2**62, (batch,), generator=gen)
    eng.reset(torch.ones(batch, dtype=torch.bool, device=device), seeds.to(device))
    placements = afterstates = 0
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps < 3:
        feats, mask, term, _ = eng.afterstates()
        alive = torch.as_tensor(eng.alive).clone()
        action = greedy_placement(batched_values(w, feats), mask, term)
        eng.step(action)
        placements += int(alive.sum())
        afterstates += int(mask.sum())
        dead = ~torch.as_tensor(eng.alive)
        if dead.any():
            eng.reset(dead, torch.randint(0, 2**62, (batch,), generator=gen).to(device))
        steps += 1
    dt = time.perf_counter() - t0
    return {"placements_per_s": placements / dt, "afterstates_per_s": afterstates / dt}


def bench_env(rules: TetrisRules, batch: int, seconds: float) -> dict[str, float]:
    """The TorchRL env: step_and_maybe_reset with a greedy BT policy on the observation."""
    env = TetrisEnv(batch=batch, rules=rules, features="bt")
    w = bt_policy(rules.width).expand(batch, -1)
    td = env.reset()
    placements = afterstates = 0
    steps, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or steps < 3:
        v = batched_values(w, td[keys.AFTERSTATE_FEATURES])
        td[keys.ACTION] = greedy_placement(v, td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL])
        placements += batch
        afterstates += int(td[keys.ACTION_MASK].sum())
        _, td = env.step_and_maybe_reset(td)
        steps += 1
    dt = time.perf_counter() - t0
    return {"placements_per_s": placements / dt, "afterstates_per_s": afterstates / dt}


def bench_tetris_gymnasium(seconds: float) -> dict[str, float] | str:
    """tetris-gymnasium's GroupedActionsObservations wrapper (placement level), random legal placements."""
    try:
        import gymnasium as gym
        import numpy as np
        from tetris_gymnasium.envs import Tetris  # noqa: F401  (registers the id)
        from tetris_gymnasium.wrappers.grouped import GroupedActionsObservations
        from tetris_gymnasium.wrappers.observation import FeatureVectorObservation
    except ImportError:
        return "not installed: pip install -e '.[bench]'"
    env = gym.make("tetris_gymnasium/Tetris")
    env = GroupedActionsObservations(env, observation_wrappers=[FeatureVectorObservation(env)])
    rng = np.random.default_rng(0)
    _, info = env.reset(seed=0)
    placements, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        legal = np.flatnonzero(info["action_mask"])
        _, _, term, trunc, info = env.step(int(rng.choice(legal)))
        placements += 1
        if term or trunc:
            _, info = env.reset()
    dt = time.perf_counter() - t0
    return {"placements_per_s": placements / dt, "afterstates_per_s": placements * 4 * 10 / dt}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=3.0, help="time per measurement")
    p.add_argument("--width", type=int, default=10)
    p.add_argument("--height", type=int, default=20)
    p.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024])
    args = p.parse_args()
    rules = TetrisRules(args.width, args.height)
    out: dict[str, object] = {
        "board": f"{args.width}x{args.height}",
        "rules": rules.describe(),
        "features": "bt",
        "threads": 1,
        "machine": platform.processor() or platform.machine(),
        "torch": torch.__version__,
        "numba": numba.__version__,
    }
    out["numba_fused_games"] = bench_fused(rules, args.seconds)
    out["numba_engine"] = {f"B={b}": bench_engine(rules, b, args.seconds, "numba") for b in args.batches}
    out["torchrl_env"] = {f"B={b}": bench_env(rules, b, args.seconds) for b in args.batches}
    try:
        out["torch_engine_cpu"] = {
            f"B={b}": bench_engine(rules, b, args.seconds, "torch") for b in args.batches
        }
    except ImportError as exc:
        out["torch_engine_cpu"] = f"unavailable: {exc}"
    if torch.cuda.is_available():
        big = [*args.batches, 16384]
        out["torch_engine_cuda"] = {
            f"B={b}": bench_engine(rules, b, args.seconds, "torch", "cuda") for b in big
        }
    ref = bench_tetris_gymnasium(args.seconds)
    out["tetris_gymnasium_grouped"] = ref
    if isinstance(ref, dict):
        base = ref["placements_per_s"]
        best_env = max(v["placements_per_s"] for v in out["torchrl_env"].values())
        out["ratio_fused_vs_tetris_gymnasium"] = out["numba_fused_games"]["placements_per_s"] / base
        out["ratio_torchrl_env_vs_tetris_gymnasium"] = best_env / base
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
