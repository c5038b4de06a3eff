"""``evaluate.py`` on keepaway: play N episodes of a benchmark policy or a learned checkpoint and summarise
them."""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModuleBase

from hfrl_torch.agents.policies import load_policy
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import CheckpointError, ConfigError
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.keepaway import (
    KeepawayConfig,
    KeepawayEnv,
    make_benchmark_policy,
    play_benchmark_policy,
    play_keeper_policy,
    record_episode_gif,
    record_keeper_gif,
    saved_config,
)
from hfrl_torch.envs.keepaway.benchmark_policies import CYCLES_PER_SECOND
from hfrl_torch.experiment.checks import check_kernels
from hfrl_torch.experiment.command_line import task_overrides
from hfrl_torch.experiment.factories import make_keepaway_config, set_threads
from hfrl_torch.experiment.learners.keepaway_dqn import play_episodes

KEEPAWAY_POLICIES = ("hand", "random", "hold")  # besides a keepaway run directory or checkpoint file


def evaluate_keepaway(cfg: DictConfig, progress: bool = True) -> dict[str, object]:
    """Play ``episodes`` episodes of a keeper policy and return the JSON summary.

    ``policy`` is a benchmark policy (hand, random, hold; played on the task ``domain`` sets) or a
    keepaway run directory or checkpoint file (Sarsa or DQN keepers), played greedily (no exploration, no
    learning; a trainer's run by its fusion rule), as :func:`~hfrl_torch.agents.policies.load_policy` loads
    it. A checkpoint is played on the
    task it learned, its saved ``domain_config``: only ``domain.batch``, ``domain.kernels`` (how it runs),
    ``episodes`` and ``seed`` come from the command line, and other ``domain.*`` values there are refused
    rather than ignored. Field f plays for
    the checkpoint's team f % teams; the summary then adds ``teams`` and ``per_team_mean_s``.
    """
    policy = "hand" if cfg.policy is None else str(cfg.policy)
    if policy in KEEPAWAY_POLICIES:
        config = make_keepaway_config(cfg)
        set_threads(cfg)
        return _play_benchmark(cfg, policy, config, progress)
    ckpt, config = _keepaway_checkpoint(policy)
    config = config.replace(kernels=check_kernels(cfg))
    set_threads(cfg)
    return evaluate_keepaway_checkpoint(cfg, ckpt, config, progress, label=policy)


def _task(cfg: DictConfig, config: KeepawayConfig) -> dict[str, Any]:
    """The keyword arguments of the batched simulator's players for ``config``'s task."""
    options = asdict(config)
    options.pop("preset"), options.pop("keepers"), options.pop("takers")
    task = {"preset": config.preset, "keepers": config.keepers, "takers": config.takers, **options}
    cap_s = OmegaConf.select(cfg, "max_episode_s")
    task["cap_cycles"] = None if cap_s is None else max(1, round(float(cap_s) * CYCLES_PER_SECOND))
    return task


def _play_benchmark(
    cfg: DictConfig, policy: str, config: KeepawayConfig, progress: bool
) -> dict[str, object]:
    episodes, seed, batch = int(cfg.episodes), int(cfg.seed), int(cfg.domain.batch)
    task = _task(cfg, config)
    result = play_benchmark_policy(policy, episodes, batch=batch, seed=seed, progress=progress, **task)
    if cfg.gif:
        gen = torch.Generator().manual_seed(seed)
        benchmark = make_benchmark_policy(policy, config.keepers, config.takers, gen)
        path, cycles = record_episode_gif(cfg.gif, benchmark, config, seed=seed)
        result["gif"] = str(path)
        result["gif_episode_s"] = cycles / 10.0
    return result


def evaluate_keepaway_checkpoint(
    cfg: DictConfig,
    ckpt: dict[str, Any],
    config: KeepawayConfig,
    progress: bool = True,
    label: str | None = None,
) -> dict[str, object]:
    """Play ``episodes`` episodes of a keepaway checkpoint's policy
    (:func:`~hfrl_torch.agents.policies.load_policy`) on ``config``'s task: by the batched simulator where
    the policy has a keeper chooser (Sarsa keepers; ``domain.batch`` fields at a time, ``gif`` drawn with
    it), else as its TorchRL module stepping one field per episode (DQN)."""
    seed = int(cfg.seed)
    generator = torch.Generator().manual_seed(seed + 1)  # the chooser's tie breaks while it plays
    module, info = load_policy(ckpt, "cpu", generator)
    label = ckpt["path"] if label is None else label
    if info["chooser"] is None:
        return _play_module(cfg, module, info, config, label)
    episodes, batch = int(cfg.episodes), int(cfg.domain.batch)
    result = play_keeper_policy(
        info["chooser"],
        label,
        episodes,
        batch=batch,
        seed=seed,
        progress=progress,
        teams=info["teams"],
        **_task(cfg, config),
    )
    if cfg.gif:
        generator.manual_seed(seed)  # the episode drawn gets its own tie breaks, as a fresh load's
        path, cycles = record_keeper_gif(cfg.gif, info["chooser"], config, seed=seed)
        result["gif"] = str(path)
        result["gif_episode_s"] = cycles / 10.0
    return result


def _play_module(
    cfg: DictConfig, module: TensorDictModuleBase, info: dict[str, Any], config: KeepawayConfig, label: str
) -> dict[str, object]:
    """One fresh episode per field of ``KeepawayEnv``, greedily by ``module``."""
    episodes = int(cfg.episodes)
    env = KeepawayEnv(episodes, config, seed=int(cfg.seed), sync="all")
    t0 = time.perf_counter()
    seconds, cause = play_episodes(env, module, info["fusion"])
    elapsed = time.perf_counter() - t0
    s = summarize(seconds, floor=0.0)
    return {
        "domain": "keepaway",
        "policy": label,
        "preset": config.preset,
        "keepers": config.keepers,
        "takers": config.takers,
        "episodes": episodes,
        "mean_s": s["mean"],
        "sd_s": s["sd"],
        "median_s": s["median"],
        "ci95_low": s["ci95_low"],
        "ci95_high": s["ci95_high"],
        "taken_share": float((cause == 2).double().mean()),
        "out_share": float((cause == 1).double().mean()),
        "cycles_per_s": float(seconds.sum()) * 10.0 / max(elapsed, 1e-9),
        "seed": int(cfg.seed),
    }


def _keepaway_checkpoint(policy: str) -> tuple[dict[str, Any], KeepawayConfig]:
    """The keepaway checkpoint that ``policy`` (a run directory or checkpoint file) names and the task it
    learned (a ``KeepawayConfig``); one-line errors."""
    if not policy.strip() or not Path(policy).exists():
        raise ConfigError(
            f"policy={policy!r} is not a keepaway policy; allowed: {', '.join(KEEPAWAY_POLICIES)}, "
            "or a keepaway run directory or checkpoint file"
        )
    free = ("domain.batch=", "domain.kernels=")  # how it runs, not what task
    explicit = [o for o in task_overrides() if o.startswith("domain.") and not o.startswith(free)]
    if explicit:
        raise ConfigError(
            f"{explicit[0]} does not apply to a checkpoint, which is played on the task it learned "
            "(set only domain.batch, domain.kernels, episodes and seed)"
        )
    ckpt = load_checkpoint(policy, domain="keepaway")
    try:
        config = saved_config(ckpt["domain_config"])
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"checkpoint {ckpt['path']!r} holds no valid keepaway task ({e})") from None
    return ckpt, config


def format_keepaway_summary(r: dict[str, object]) -> str:
    """Human-readable lines above the final JSON line."""
    ci = f"{r['ci95_low']:.2f}..{r['ci95_high']:.2f}"
    out = [
        f"keepaway {r['keepers']}v{r['takers']} ({r['preset']} preset): {r['policy']} policy",
        f"  {r['episodes']} episodes: mean {r['mean_s']:.2f} s, 95% CI {ci}, "
        f"median {r['median_s']:.2f} s, sd {r['sd_s']:.2f} s",
        f"  ended by takers {100 * r['taken_share']:.0f} %, out of bounds {100 * r['out_share']:.0f} %; "
        f"{r['cycles_per_s']:.0f} simulated cycles/s",
    ]
    if r.get("cut_share"):
        out.append(
            f"  cut at max_episode_s, still running: {100 * r['cut_share']:.1f} % (counted at that length)"
        )
    if "teams" in r:
        means = [m for m in r["per_team_mean_s"] if m is not None]
        shown = (
            ", ".join(f"{m:.2f}" for m in means)
            if len(means) <= 10
            else f"{min(means):.2f}..{max(means):.2f}"
        )
        unplayed = len(r["per_team_mean_s"]) - len(means)
        out.append(
            f"  {r['teams']} teams, greedy (field f plays for team f % {r['teams']}): mean per team {shown} s"
            + (f" ({unplayed} teams had no field: raise episodes or domain.batch)" if unplayed else "")
        )
    if "gif" in r:
        out.append(f"  one episode ({r['gif_episode_s']:.1f} s) drawn to {r['gif']}")
    return "\n".join(out)
