"""Episodes of the benchmark keeper policies (Random, Always Hold, Hand-coded), played
directly on the batched simulator with the policy deciding inside each cycle."""

from __future__ import annotations

import math
import statistics
import time
from typing import Any

import torch
from tqdm import tqdm

from hfrl_torch.envs.keepaway.params import KeepawayConfig
from hfrl_torch.envs.keepaway.policies import make_benchmark_policy
from hfrl_torch.envs.keepaway.referee import END_OUT, END_TAKEN
from hfrl_torch.envs.keepaway.simulator import KeepawaySimulator

CYCLES_PER_SECOND = 10.0


def play_benchmark_policy(
    policy: str,
    episodes: int,
    *,
    preset: str = "2005",
    keepers: int = 3,
    takers: int = 2,
    batch: int = 256,
    seed: int = 0,
    device: str = "cpu",
    progress: bool = True,
    **sim_options: Any,
) -> dict[str, Any]:
    """Play ``episodes`` episodes of benchmark ``policy`` ("random", "hold" or "hand") and
    summarise their durations in simulated seconds.

    Every field plays the same number of consecutive episodes (ceil(episodes / batch)) and the
    first ``episodes`` of them, by field then order, are kept, so long episodes are not cut
    short by the stopping rule. The 95 % interval is mean +- 1.96 sd / sqrt(N).

    :param sim_options: further :class:`KeepawayConfig` fields (``length``, ``width``,
        ``turnover_cycles``, ``movement_noise``, ``noisy_observations``, ...).
    :returns: domain, policy, preset, keepers, takers, episodes, mean_s, sd_s, median_s,
        ci95_low, ci95_high, taken_share, out_share, cycles_per_s.
    """
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    config = KeepawayConfig(preset=preset, keepers=keepers, takers=takers, **sim_options)
    batch = max(1, min(batch, episodes))
    quota = math.ceil(episodes / batch)
    sim = KeepawaySimulator(batch, config, device=device, seed=seed)
    generator = torch.Generator(device=sim.device)
    generator.manual_seed(seed + 1)
    choose = make_benchmark_policy(policy, keepers, takers, generator)
    played = torch.zeros(batch, dtype=torch.long, device=sim.device)
    durations = torch.zeros(batch, quota, dtype=torch.long, device=sim.device)
    causes = torch.zeros(batch, quota, dtype=torch.long, device=sim.device)
    active = torch.ones(batch, dtype=torch.bool, device=sim.device)
    field_cycles = 0
    bar = tqdm(total=batch * quota, desc=f"keepaway {policy}", disable=not progress, unit="ep")
    start = time.perf_counter()
    while bool(active.any()):
        holder = sim.decision().holder
        obs, _ = sim.observe(holder)
        out = sim.step(choose(obs), active=active, auto_reset=True)
        field_cycles += int(active.sum())
        if bool(out.ended.any()):
            rows = out.ended.nonzero().squeeze(-1)
            slot = played[rows]
            durations[rows, slot] = out.episode_cycles[rows]
            causes[rows, slot] = out.end_cause[rows]
            played[rows] += 1
            active = played < quota
            bar.update(int(rows.numel()))
    elapsed = time.perf_counter() - start
    bar.close()
    kept_durations = durations.reshape(-1)[:episodes].double().cpu() / CYCLES_PER_SECOND
    kept_causes = causes.reshape(-1)[:episodes].cpu()
    values = kept_durations.tolist()
    mean = statistics.fmean(values)
    sd = statistics.stdev(values) if len(values) > 1 else 0.0
    half = 1.96 * sd / math.sqrt(len(values))
    return {
        "domain": "keepaway",
        "policy": policy,
        "preset": preset,
        "keepers": keepers,
        "takers": takers,
        "episodes": episodes,
        "mean_s": mean,
        "sd_s": sd,
        "median_s": statistics.median(values),
        "ci95_low": mean - half,
        "ci95_high": mean + half,
        "taken_share": float((kept_causes == END_TAKEN).double().mean()),
        "out_share": float((kept_causes == END_OUT).double().mean()),
        "cycles_per_s": field_cycles / elapsed if elapsed > 0 else float("nan"),
    }
