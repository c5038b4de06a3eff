"""Episodes of keeper policies (the benchmark Random, Always Hold and Hand-coded, or a learned
checkpoint's), played directly on the batched simulator with the policy deciding inside each cycle."""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from tqdm import tqdm

from hfrl_torch.envs.keepaway.params import KeepawayConfig
from hfrl_torch.envs.keepaway.policies import make_benchmark_policy
from hfrl_torch.envs.keepaway.referee import END_OUT, END_RUNNING, END_TAKEN
from hfrl_torch.envs.keepaway.render import render_rgb, write_gif
from hfrl_torch.envs.keepaway.simulator import KeepawaySimulator

CYCLES_PER_SECOND = 10.0


KeeperChooser = Callable[[Tensor, Tensor, Tensor], Tensor]
"""``choose(obs [B, F], mask [B, A] bool, holder [B] long) -> actions [B]``: the action of the keeper with
the ball on every field (read by the simulator only where that keeper must decide)."""


def play_benchmark_policy(
    policy: str,
    episodes: int,
    *,
    keepers: int = 3,
    takers: int = 2,
    seed: int = 0,
    device: str = "cpu",
    **options: Any,
) -> dict[str, Any]:
    """Play ``episodes`` episodes of benchmark ``policy`` ("random", "hold" or "hand"): the other
    keyword arguments and the summary are :func:`play_keeper_policy`'s (Random draws from a
    generator seeded ``seed + 1``)."""
    generator = torch.Generator(device=device)
    generator.manual_seed(seed + 1)
    benchmark = make_benchmark_policy(policy, keepers, takers, generator)

    def choose(obs: Tensor, mask: Tensor, holder: Tensor) -> Tensor:
        return benchmark(obs)

    return play_keeper_policy(
        choose, policy, episodes, keepers=keepers, takers=takers, seed=seed, device=device, **options
    )


def play_keeper_policy(
    choose: KeeperChooser,
    name: str,
    episodes: int,
    *,
    preset: str = "2005",
    keepers: int = 3,
    takers: int = 2,
    batch: int = 256,
    seed: int = 0,
    device: str = "cpu",
    progress: bool = True,
    teams: int | None = None,
    cap_cycles: int | None = None,
    **sim_options: Any,
) -> dict[str, Any]:
    """Play ``episodes`` episodes of keeper policy ``choose`` (called every cycle on every field, see
    :data:`KeeperChooser`; all actions are available) and summarise their durations in simulated seconds.

    Every field plays the same number of consecutive episodes (ceil(episodes / batch)) and the
    first ``episodes`` of them, by field then order, are kept, so long episodes are not cut
    short by the stopping rule. The 95 % interval is mean +- 1.96 sd / sqrt(N).

    :param name: the policy's label in the result and the progress bar.
    :param teams: field f plays for team f % teams (a learned checkpoint's learners); the result then
        also holds ``teams`` and ``per_team_mean_s`` (None for a team without a kept episode).
    :param cap_cycles: cut an episode that reaches this many cycles (counted at that length, neither
        taken nor out; the result then also holds ``cut_share``), for policies whose episodes may
        never end.
    :param sim_options: further :class:`KeepawayConfig` fields (``length``, ``width``,
        ``turnover_cycles``, ``movement_noise``, ``noisy_observations``, ...).
    :returns: domain, policy, preset, keepers, takers, episodes, mean_s, sd_s, median_s,
        ci95_low, ci95_high, taken_share, out_share, cycles_per_s.
    """
    if episodes < 1:
        raise ValueError("episodes must be >= 1")
    if teams is not None and teams < 1:
        raise ValueError("teams must be >= 1")
    config = KeepawayConfig(preset=preset, keepers=keepers, takers=takers, **sim_options)
    batch = max(1, min(batch, episodes))
    quota = math.ceil(episodes / batch)
    sim = KeepawaySimulator(batch, config, device=device, seed=seed)
    mask = torch.ones(batch, config.num_actions, dtype=torch.bool, device=sim.device)
    played = torch.zeros(batch, dtype=torch.long, device=sim.device)
    durations = torch.zeros(batch, quota, dtype=torch.long, device=sim.device)
    causes = torch.zeros(batch, quota, dtype=torch.long, device=sim.device)
    active = torch.ones(batch, dtype=torch.bool, device=sim.device)
    field_cycles = 0
    bar = tqdm(total=batch * quota, desc=f"keepaway {name}", disable=not progress, unit="ep")
    start = time.perf_counter()
    while bool(active.any()):
        holder = sim.decision().holder
        obs, _ = sim.observe(holder)
        out = sim.step(choose(obs, mask, holder), active=active, auto_reset=False)
        field_cycles += int(active.sum())
        if cap_cycles is not None:
            out.ended = out.ended | (active & (out.episode_cycles >= cap_cycles))
        if bool(out.ended.any()):
            sim.reset(out.ended)
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
    result = {
        "domain": "keepaway",
        "policy": name,
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
    if cap_cycles is not None:
        result["cut_share"] = float((kept_causes == END_RUNNING).double().mean())
    if teams is not None:
        team = torch.div(torch.arange(episodes), quota, rounding_mode="floor") % teams
        result["teams"] = teams
        result["per_team_mean_s"] = [
            float(kept_durations[team == t].mean()) if bool((team == t).any()) else None for t in range(teams)
        ]
    return result


def record_keeper_gif(
    path: str | Path,
    choose: KeeperChooser,
    config: KeepawayConfig | None = None,
    seed: int = 0,
    max_cycles: int = 600,
    fps: int = 10,
) -> tuple[Path, int]:
    """Play one episode on one field (team 0) with ``choose`` and save it as a GIF; returns the path and
    the episode length in cycles. :func:`record_episode_gif` for choosers that need the holder."""
    sim = KeepawaySimulator(1, config, seed=seed)
    mask = torch.ones(1, sim.config.num_actions, dtype=torch.bool, device=sim.device)
    frames = [render_rgb(sim.state, 0, sim.config)]
    cycles = 0
    for _ in range(max_cycles):
        holder = sim.decision().holder
        obs, _ = sim.observe(holder)
        out = sim.step(choose(obs, mask, holder))
        frames.append(render_rgb(sim.state, 0, sim.config))
        cycles = int(out.episode_cycles[0])
        if bool(out.ended[0]):
            break
    return write_gif(frames, path, fps), cycles
