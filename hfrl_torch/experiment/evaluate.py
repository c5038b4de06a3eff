"""What ``evaluate.py`` does: play N games of a checkpoint or a named reference policy and report."""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch.agents.cem.fused_rollout import FusedRollout
from hfrl_torch.agents.sarsa.policy import load_keeper_policy
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import CheckpointError, ConfigError
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.keepaway import (
    KeepawayConfig,
    make_benchmark_policy,
    play_benchmark_policy,
    play_keeper_policy,
    record_episode_gif,
    record_keeper_gif,
)
from hfrl_torch.envs.keepaway.benchmark_policies import CYCLES_PER_SECOND
from hfrl_torch.envs.tetris.features import DELLACHERIE_WEIGHTS, feature_id, feature_size
from hfrl_torch.experiment.aggregate import aggregate
from hfrl_torch.experiment.cli import checked
from hfrl_torch.experiment.config import check_kernels, validate_evaluate
from hfrl_torch.experiment.dqn_players import evaluate_dqn_keepaway, evaluate_dqn_tetris, is_dqn
from hfrl_torch.experiment.factories import (
    make_keepaway_config,
    make_rollout,
    make_rules,
    set_threads,
    warm_up,
)
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight

NAMED_POLICIES = ("dellacherie", "random")


def _tetris_policy(cfg: DictConfig) -> tuple[str, str, torch.Tensor, bool, DictConfig, dict | None]:
    """(policy label, feature set, weights, random?, config with the checkpoint's board, the fused policy's
    H^ part or None) of ``policy``."""
    name = "dellacherie" if cfg.policy is None else str(cfg.policy)
    if name == "dellacherie":
        return name, "dellacherie", torch.tensor(DELLACHERIE_WEIGHTS, dtype=torch.float64), False, cfg, None
    if name == "random":
        w = torch.zeros(feature_size(feature_id("bt"), cfg.domain.width), dtype=torch.float64)
        return name, "bt", w, True, cfg, None
    path = Path(name)
    if not name.strip() or not path.exists():
        raise ConfigError(
            f"policy={name!r} is neither a checkpoint nor a run directory nor one of: dellacherie, random"
        )
    ckpt = load_checkpoint(path, domain="tetris")
    policy = ckpt["policy"]
    # the checkpoint's board and rules, unless this command line sets domain values itself
    explicit = [o for o in _task_overrides() if o.startswith("domain.")]
    saved = OmegaConf.create(ckpt["config"])
    cfg = OmegaConf.merge(cfg, {"domain": saved.domain}, OmegaConf.from_dotlist(explicit))
    return (
        ckpt["path"],
        policy["features"],
        torch.as_tensor(policy["weights"], dtype=torch.float64),
        False,
        cfg,
        policy if policy.get("kind") == "fused" else None,
    )


def _task_overrides() -> list[str]:
    try:
        return list(HydraConfig.get().overrides.task)
    except ValueError:  # called outside a Hydra app (tests)
        return []


def evaluate_tetris(cfg: DictConfig, progress: bool = True) -> dict[str, object]:
    """Play ``games`` games of ``policy`` and return the summary that evaluate.py prints as JSON."""
    games = int(cfg.games)
    threads = set_threads(cfg)
    if cfg.policy is not None and str(cfg.policy) not in NAMED_POLICIES and Path(str(cfg.policy)).exists():
        ckpt = load_checkpoint(Path(str(cfg.policy)), domain="tetris")
        if is_dqn(ckpt):
            explicit = [o for o in _task_overrides() if o.startswith("domain.")]
            saved = OmegaConf.create(ckpt["config"])
            board = OmegaConf.merge(cfg, {"domain": saved.domain}, OmegaConf.from_dotlist(explicit))
            return evaluate_dqn_tetris(board, ckpt, ckpt["path"])
    label, features, weights, random_policy, cfg, fused = _tetris_policy(cfg)
    rules = make_rules(cfg)
    if weights.numel() != feature_size(feature_id(features), rules.width):
        raise ConfigError(
            f"policy {label!r} has {weights.numel()} weights for features {features!r}, "
            f"which need {feature_size(feature_id(features), rules.width)} on a board {rules.width} wide"
        )
    rollout = make_rollout(cfg, features=features, random_policy=random_policy)
    feature_label = features
    if fused is not None:
        weight = float(fused["weight"])
        fusion = Fusion(
            fused["scheme"],
            "none",
            ConstantWeight(weight),
            scaling="decision" if fused["normalise"] else "none",
        )
        rollout = FusedRollout(rules, features, fused["human_features"], fusion.eval(), cfg.domain.max_pieces)
        rollout.human_weights = torch.as_tensor(fused["human_weights"], dtype=torch.float64)
        feature_label = (
            f"{features} fused with H^ over {fused['human_features']} ({fused['scheme']}, w={weight:.3g})"
        )
    gen = torch.Generator().manual_seed(int(cfg.seed))
    seeds = torch.randint(0, 2**62, (games,), generator=gen, dtype=torch.int64)

    lines, pieces, capped_list = [], [], []
    chunk = max(threads, -(-games // 20))  # about 20 progress updates
    warm_up(cfg, features)
    t0 = time.perf_counter()
    with tqdm(total=games, desc=f"eval {Path(label).name}", unit="game", disable=not progress) as bar:
        for i in range(0, games, chunk):
            s = seeds[i : i + chunk]
            ln, pc, cp, *_ = rollout(weights.expand(len(s), -1), s)
            lines.append(ln)
            pieces.append(pc)
            capped_list.append(cp)
            bar.update(len(s))
            bar.set_postfix(mean_lines=f"{torch.cat(lines).double().mean():.1f}")
    elapsed = time.perf_counter() - t0
    lines_t, pieces_t = torch.cat(lines), torch.cat(pieces)
    cap = int(cfg.domain.max_pieces)
    capped = int(torch.cat(capped_list).sum())
    s = summarize(lines_t, floor=0.0)
    return {
        "domain": "tetris",
        "policy": label,
        "features": feature_label,
        "rules": rules.describe(),
        "board": f"{rules.width}x{rules.height}",
        "games": games,
        "mean": s["mean"],
        "sd": s["sd"],
        "median": s["median"],
        "ci95_low": s["ci95_low"],
        "ci95_high": s["ci95_high"],
        "max_pieces": cap,
        "capped_games": capped,
        "pieces_per_game": float(pieces_t.double().mean()),
        "placements_per_s": float(pieces_t.sum()) / max(elapsed, 1e-9),
        "seed": int(cfg.seed),
    }


def format_summary(r: dict[str, object]) -> str:
    """Human-readable lines above the final JSON line."""
    ci = f"{r['ci95_low']:.1f}..{r['ci95_high']:.1f}"
    out = [
        f"{r['domain']}: {r['policy']} on {r['board']} ({r['rules']} rules, {r['features']} features)",
        f"  {r['games']} games: mean {r['mean']:.1f} lines per game, 95% CI {ci}, "
        f"median {r['median']:.1f}, sd {r['sd']:.1f}",
        f"  {r['pieces_per_game']:.0f} pieces per game, {r['placements_per_s']:.0f} placements/s",
    ]
    if r.get("max_pieces"):
        out.append(
            f"  games capped at {r['max_pieces']} pieces: {r['capped_games']} of {r['games']} "
            "reached the cap (their lines are a lower bound)"
        )
    return "\n".join(out)


def evaluate(cfg: DictConfig) -> dict[str, object]:
    """Evaluate and print the summary, then one JSON line on stdout."""
    if not checked():
        validate_evaluate(cfg)
    if cfg.get("runs") is not None:
        result = aggregate(cfg)
        print(json.dumps(result), flush=True)
        return result
    if cfg.domain.name == "tetris":
        result = evaluate_tetris(cfg)
        print(format_summary(result))
    else:
        result = evaluate_keepaway(cfg)
        print(format_keepaway_summary(result))
    print(json.dumps(result), flush=True)
    return result


KEEPAWAY_POLICIES = ("hand", "random", "hold")  # besides a keepaway run directory or checkpoint file


def evaluate_keepaway(cfg: DictConfig, progress: bool = True) -> dict[str, object]:
    """Play ``episodes`` episodes of a keeper policy and return the JSON summary.

    ``policy`` is a benchmark policy (hand, random, hold; played on the task ``domain`` sets) or a
    keepaway Sarsa run directory or checkpoint file, played greedily (no exploration, no learning; a
    trainer's run by its fusion rule, :mod:`hfrl_torch.agents.sarsa.policy`). A checkpoint is played on the
    task it learned, its saved ``domain_config``: only ``domain.batch``, ``domain.kernels`` (how it runs),
    ``episodes`` and ``seed`` come from the command line, and other ``domain.*`` values there are refused
    rather than ignored. Field f plays for
    the checkpoint's team f % teams; the summary then adds ``teams`` and ``per_team_mean_s``.
    """
    policy = "hand" if cfg.policy is None else str(cfg.policy)
    episodes, seed, batch = int(cfg.episodes), int(cfg.seed), int(cfg.domain.batch)
    ckpt = None
    if policy in KEEPAWAY_POLICIES:
        config = make_keepaway_config(cfg)
    else:
        ckpt, config = _keepaway_checkpoint(policy)
        config = config.replace(kernels=check_kernels(cfg))
    set_threads(cfg)
    if ckpt is not None and is_dqn(ckpt):
        return evaluate_dqn_keepaway(cfg, ckpt, config, ckpt["path"])
    options = asdict(config)
    options.pop("preset"), options.pop("keepers"), options.pop("takers")
    task = {"preset": config.preset, "keepers": config.keepers, "takers": config.takers, **options}
    cap_s = OmegaConf.select(cfg, "max_episode_s")
    task["cap_cycles"] = None if cap_s is None else max(1, round(float(cap_s) * CYCLES_PER_SECOND))
    if ckpt is None:
        result = play_benchmark_policy(policy, episodes, batch=batch, seed=seed, progress=progress, **task)
    else:
        chooser, info = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(seed + 1))
        result = play_keeper_policy(
            chooser, policy, episodes, batch=batch, seed=seed, progress=progress, teams=info["teams"], **task
        )
    if cfg.gif:
        if ckpt is None:
            gen = torch.Generator().manual_seed(seed)
            benchmark = make_benchmark_policy(policy, config.keepers, config.takers, gen)
            path, cycles = record_episode_gif(cfg.gif, benchmark, config, seed=seed)
        else:
            chooser, _ = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(seed))
            path, cycles = record_keeper_gif(cfg.gif, chooser, config, seed=seed)
        result["gif"] = str(path)
        result["gif_episode_s"] = cycles / 10.0
    return result


def _keepaway_checkpoint(policy: str) -> tuple[dict[str, Any], KeepawayConfig]:
    """The keepaway checkpoint that ``policy`` (a run directory or checkpoint file) names and the task it
    learned (a ``KeepawayConfig``); one-line errors."""
    if not policy.strip() or not Path(policy).exists():
        raise ConfigError(
            f"policy={policy!r} is not a keepaway policy; allowed: {', '.join(KEEPAWAY_POLICIES)}, "
            "or a keepaway run directory or checkpoint file"
        )
    free = ("domain.batch=", "domain.kernels=")  # how it runs, not what task
    explicit = [o for o in _task_overrides() if o.startswith("domain.") and not o.startswith(free)]
    if explicit:
        raise ConfigError(
            f"{explicit[0]} does not apply to a checkpoint, which is played on the task it learned "
            "(set only domain.batch, domain.kernels, episodes and seed)"
        )
    ckpt = load_checkpoint(policy, domain="keepaway")
    try:
        config = KeepawayConfig(**ckpt["domain_config"])
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
