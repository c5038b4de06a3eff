"""``evaluate.py`` on Tetris: play N games of a checkpoint or a named reference policy and summarise them."""

from __future__ import annotations

import time
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch.agents.cem.fused_rollout import FusedRollout
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.tetris.features import DELLACHERIE_WEIGHTS, feature_id, feature_size
from hfrl_torch.experiment.command_line import task_overrides
from hfrl_torch.experiment.dqn_players import evaluate_dqn_tetris, is_dqn
from hfrl_torch.experiment.factories import make_rollout, make_rules, set_threads, warm_up
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
    explicit = [o for o in task_overrides() if o.startswith("domain.")]
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


def evaluate_tetris(cfg: DictConfig, progress: bool = True) -> dict[str, object]:
    """Play ``games`` games of ``policy`` and return the summary that evaluate.py prints as JSON."""
    games = int(cfg.games)
    threads = set_threads(cfg)
    if cfg.policy is not None and str(cfg.policy) not in NAMED_POLICIES and Path(str(cfg.policy)).exists():
        ckpt = load_checkpoint(Path(str(cfg.policy)), domain="tetris")
        if is_dqn(ckpt):
            explicit = [o for o in task_overrides() if o.startswith("domain.")]
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
