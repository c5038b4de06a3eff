"""Training loop of the cross-entropy Tetris agent: iterate, log, checkpoint, resume."""

from __future__ import annotations

import json
import time
from pathlib import Path

from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch.agents.cem import CrossEntropyMethod
from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.logger import flatten_config, markdown_table
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.tetris.features import feature_id, feature_names
from hfrl_torch.experiment.factories import (
    make_cem_config,
    make_rollout,
    make_rules,
    make_run_logger,
    warm_up,
)


def train_cem(cfg: DictConfig, run_dir: Path, checkpoint: dict | None) -> dict[str, float]:
    """Run CE iterations up to ``agent.iterations``, continuing from ``checkpoint`` if given."""
    rules = make_rules(cfg)
    cem_cfg = make_cem_config(cfg)
    rollout = make_rollout(cfg)
    names = feature_names(feature_id(cfg.domain.features), rules.width)
    cem = CrossEntropyMethod(len(names), cem_cfg, rollout, seed=cfg.seed)
    history: list[dict[str, float]] = []
    if checkpoint is not None:
        cem.load_state_dict(checkpoint["state"])
        history = list(checkpoint["history"])

    start = cem.iteration
    warm_up(cfg)
    logger = make_run_logger(cfg, str(run_dir / "tensorboard"), purge_step=start + 1 if start > 0 else None)
    if start == 0:
        logger.text("hyperparameters", markdown_table(flatten_config(cfg)))
        logger.text(
            "rules", f"{rules.describe()}, board {rules.width}x{rules.height}, features {cfg.domain.features}"
        )
    metrics_file = run_dir / "metrics.jsonl"
    ckpt_path = run_dir / "checkpoints" / LAST
    config_yaml = OmegaConf.to_yaml(cfg, resolve=True)

    bar = tqdm(
        total=cfg.agent.iterations,
        initial=start,
        desc=f"CE {rules.width}x{rules.height}",
        unit="it",
        dynamic_ncols=True,
    )
    try:
        while cem.iteration < cfg.agent.iterations:
            t0 = time.perf_counter()
            metrics = cem.step()
            eval_lines = cem.evaluate_mean()
            elapsed = time.perf_counter() - t0
            ev = summarize(eval_lines, floor=0.0)
            placements = metrics["population/placements"] + cem.last_eval_pieces
            metrics.update(
                {
                    "eval/mean_policy_lines_mean": ev["mean"],
                    "eval/mean_policy_lines_median": ev["median"],
                    "eval/mean_policy_lines_ci95_low": ev["ci95_low"],
                    "eval/mean_policy_lines_ci95_high": ev["ci95_high"],
                    "eval/capped_games": cem.last_eval_capped,
                    "time/placements_per_s": placements / max(elapsed, 1e-9),
                    "time/iteration_s": elapsed,
                }
            )
            step = cem.iteration
            logger.scalars(metrics, step)
            logger.flush()
            history.append({"iteration": step, **metrics})
            save_checkpoint(
                ckpt_path,
                domain="tetris",
                agent="cem",
                config_yaml=config_yaml,
                payload={
                    "state": cem.state_dict(),
                    "history": history,
                    "policy": {
                        "kind": "linear",
                        "features": cfg.domain.features,
                        "feature_names": names,
                        "weights": cem.mean.clone(),
                    },
                    "rules": rules.as_dict(),
                },
            )
            with metrics_file.open("a") as f:
                f.write(json.dumps({"iteration": step, **metrics}) + "\n")
            bar.update(1)
            bar.set_postfix(
                eval_lines=f"{ev['mean']:.1f}",
                pop_lines=f"{metrics['population/lines_mean']:.1f}",
                noise=f"{metrics['cem/noise']:.2f}",
                pl_s=f"{metrics['time/placements_per_s']:.0f}",
            )
    finally:
        bar.close()
        final = history[-1] if history else {}
        if history and cem.iteration >= cfg.agent.iterations and cem.iteration > start:
            logger.hparams(
                flatten_config(cfg),
                {"hparam/eval_lines_mean": final["eval/mean_policy_lines_mean"]},
            )
        logger.close()
    return final
