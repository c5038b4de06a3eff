"""``evaluate.py`` on Tetris: play N games of a checkpoint or a named reference policy and summarise them.

A checkpoint's policy comes from :func:`~hfrl_torch.agents.policies.load_policy`, the one loader of every
learner's saved policy."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict.nn import TensorDictModuleBase
from tqdm import tqdm

from hfrl_torch.agents.cem.fused_rollout import FusedRollout
from hfrl_torch.agents.policies import load_policy
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.tetris.features import DELLACHERIE_WEIGHTS, feature_id, feature_size
from hfrl_torch.experiment.command_line import task_overrides
from hfrl_torch.experiment.factories import make_env, make_rollout, make_rules, set_threads, warm_up
from hfrl_torch.experiment.learners.tetris_dqn import play_games
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight

NAMED_POLICIES = ("dellacherie", "random")


def _reference(cfg: DictConfig, name: str) -> tuple[dict[str, Any], bool]:
    """A named reference policy in the compiled rollout's form, and whether it places at random."""
    if name == "dellacherie":
        return {
            "features": "dellacherie",
            "weights": torch.tensor(DELLACHERIE_WEIGHTS, dtype=torch.float64),
        }, False
    w = torch.zeros(feature_size(feature_id("bt"), cfg.domain.width), dtype=torch.float64)
    return {"features": "bt", "weights": w}, True


def _on_saved_board(cfg: DictConfig, ckpt: dict[str, Any]) -> DictConfig:
    """``cfg`` with the checkpoint's board and rules, unless this command line sets domain values itself."""
    explicit = [o for o in task_overrides() if o.startswith("domain.")]
    saved = OmegaConf.create(ckpt["config"])
    return OmegaConf.merge(cfg, {"domain": saved.domain}, OmegaConf.from_dotlist(explicit))


def evaluate_tetris(cfg: DictConfig, progress: bool = True) -> dict[str, object]:
    """Play ``games`` games of ``policy`` and return the summary that evaluate.py prints as JSON."""
    threads = set_threads(cfg)
    name = "dellacherie" if cfg.policy is None else str(cfg.policy)
    if name in NAMED_POLICIES:
        form, random_policy = _reference(cfg, name)
        return _play_afterstate(cfg, name, form, random_policy, threads, progress)
    if not name.strip() or not Path(name).exists():
        raise ConfigError(
            f"policy={name!r} is neither a checkpoint nor a run directory nor one of: dellacherie, random"
        )
    ckpt = load_checkpoint(Path(name), domain="tetris")
    return evaluate_tetris_checkpoint(_on_saved_board(cfg, ckpt), ckpt, progress, threads)


def evaluate_tetris_checkpoint(
    cfg: DictConfig, ckpt: dict[str, Any], progress: bool = True, threads: int = 1
) -> dict[str, object]:
    """Play ``games`` games of a Tetris checkpoint's policy (:func:`~hfrl_torch.agents.policies.load_policy`)
    on the board ``cfg`` sets: by the compiled rollout where the policy has its linear afterstate form
    (CE, TAMER, Q-learning, PG, fused CE), else as its TorchRL module stepping the env (DQN)."""
    module, info = load_policy(ckpt, "cpu", torch.Generator().manual_seed(int(cfg.seed)))
    if info["afterstate"] is not None:
        return _play_afterstate(cfg, ckpt["path"], info["afterstate"], False, threads, progress, info)
    return _play_module(cfg, ckpt["path"], module, info)


def _play_module(
    cfg: DictConfig, label: str, module: TensorDictModuleBase, info: dict[str, Any]
) -> dict[str, object]:
    """One fresh game per board of ``env``, greedily by ``module`` (``domain.max_pieces`` caps them)."""
    width, height = int(cfg.domain.width), int(cfg.domain.height)
    if width != info["board_width"]:
        raise ConfigError(
            f"policy {label!r} was saved for a board {info['board_width']} wide; domain.width={width} differs"
        )
    games = int(cfg.games)
    env = make_env(cfg, games, features=info["env_features"])
    env.set_seed(int(cfg.seed))
    fusion = info["fusion"] if info["fusion"] is not None else Fusion("none", "none", ConstantWeight(0.0))
    t0 = time.perf_counter()
    lines, pieces = play_games(env, module, fusion)
    elapsed = time.perf_counter() - t0
    s = summarize(lines, floor=0.0)
    rules = make_rules(cfg)
    return {
        "domain": "tetris",
        "policy": label,
        "features": info["describe"],
        "rules": rules.describe(),
        "board": f"{width}x{height}",
        "games": games,
        **{k: s[k] for k in ("mean", "sd", "median", "ci95_low", "ci95_high")},
        "max_pieces": int(cfg.domain.max_pieces),
        "capped_games": 0,
        "pieces_per_game": float(pieces.mean()),
        "placements_per_s": float(pieces.sum()) / max(elapsed, 1e-9),
        "seed": int(cfg.seed),
    }


def _play_afterstate(
    cfg: DictConfig,
    label: str,
    form: dict[str, Any],
    random_policy: bool,
    threads: int,
    progress: bool,
    info: dict[str, Any] | None = None,
) -> dict[str, object]:
    """``games`` games of a linear afterstate policy (``form``: ``features``, ``weights`` and, fused, its H^
    part) in the compiled rollout, each game's seed drawn from ``seed``."""
    games = int(cfg.games)
    features = form["features"]
    weights = form["weights"]
    rules = make_rules(cfg)
    if weights.numel() != feature_size(feature_id(features), rules.width):
        raise ConfigError(
            f"policy {label!r} has {weights.numel()} weights for features {features!r}, "
            f"which need {feature_size(feature_id(features), rules.width)} on a board {rules.width} wide"
        )
    rollout = make_rollout(cfg, features=features, random_policy=random_policy)
    feature_label = features if info is None else info["describe"]
    fused = form.get("fused")
    if fused is not None:
        fusion = Fusion(
            fused["scheme"],
            "none",
            ConstantWeight(fused["weight"]),
            scaling="decision" if fused["normalise"] else "none",
        )
        rollout = FusedRollout(rules, features, fused["human_features"], fusion.eval(), cfg.domain.max_pieces)
        rollout.human_weights = fused["human_weights"]
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
