"""Per-game curves of runs of L independent Tetris learners (TAMER, Q-learning, PG): what they log and play.

Every learner plays games 1..G; the curve at game g summarises the learners' lines in their g-th game (mean,
median, 95 % interval over learners), plus what each learner type adds. ``greedy_evaluation`` plays every
learner's policy without exploration on the same fresh games.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig

from hfrl_torch.common.logger import Logger
from hfrl_torch.common.stats import summarize


def write_game_curves(
    lines: torch.Tensor,
    logger: Logger,
    run_dir: Path,
    extra: Callable[[int], dict[str, float]] | None = None,
) -> list[dict[str, float]]:
    """Log one point per game of ``lines`` [L, G] (plus ``extra(g)``) to TensorBoard and write them to
    ``metrics.jsonl``; returns the points."""
    lines = lines.double()
    history = []
    for g in range(lines.shape[1]):
        s = summarize(lines[:, g], floor=0.0)
        metrics = {
            "eval/lines_per_game_mean": s["mean"],
            "eval/lines_per_game_median": s["median"],
            "eval/lines_per_game_ci95_low": s["ci95_low"],
            "eval/lines_per_game_ci95_high": s["ci95_high"],
            **(extra(g) if extra is not None else {}),
        }
        logger.scalars(metrics, g + 1)
        history.append({"game": g + 1, **metrics})
    with (run_dir / "metrics.jsonl").open("w") as f:
        f.writelines(json.dumps(h) + "\n" for h in history)
    return history


def greedy_evaluation(cfg: DictConfig, weights: torch.Tensor, games: int) -> dict[str, float]:
    """Each learner's greedy policy on the same ``games`` fresh games (``domain.max_pieces`` cap): the mean
    lines per game of each learner, summarised over the learners (the policies without exploration)."""
    from hfrl_torch.experiment.factories import make_rollout

    gen = torch.Generator().manual_seed(int(cfg.seed) + 10_007)  # games that training did not play
    seeds = torch.randint(0, 2**62, (games,), generator=gen, dtype=torch.int64)
    rollout = make_rollout(cfg, features=cfg.agent.features)
    learners = weights.shape[0]
    lines, _, _ = rollout(weights.repeat_interleave(games, 0), seeds.repeat(learners))
    s = summarize(lines.double().view(learners, games).mean(1), floor=0.0)
    return {f"eval/greedy_lines_{k}": s[k] for k in ("mean", "median", "ci95_low", "ci95_high")}
