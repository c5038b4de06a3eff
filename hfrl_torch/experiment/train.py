"""What ``train.py`` does: set up (or resume) a run directory, then hand over to the agent's loop."""

from __future__ import annotations

import signal
import sys
from pathlib import Path
from typing import NamedTuple

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.checkpoint import LAST, load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment.factories import set_threads, validate_train_config
from hfrl_torch.experiment.keepaway_sarsa import train_sarsa
from hfrl_torch.experiment.tetris_cem import train_cem
from hfrl_torch.experiment.tetris_cem_hf import train_cem_hf
from hfrl_torch.experiment.tetris_pg import train_pg
from hfrl_torch.experiment.tetris_qlearning import train_qlearning
from hfrl_torch.experiment.tetris_tamer import train_tamer

GROUPS = ("domain", "agent", "fusion", "human", "trainer", "logger")
TRAINER_LABELS = {
    "oracle": "simulated oracle trainer",
    "value_proxy": "simulated value-proxy trainer",
    "replay": "replayed feedback log",
    "interactive": "person in the browser",
}


RESUMABLE = (
    "agent.iterations",
    "agent.hours",
    "agent.episodes",
    "threads",
    "device",
    "domain.kernels",
    "logger.backend",
)
SAVES_AS_IT_GOES = ("cem", "sarsa")  # agents whose runs checkpoint while they train, so can resume


def resume_config(cfg: DictConfig, run_dir: Path, checkpoint: dict, overrides: list[str]) -> DictConfig:
    """The saved config of ``run_dir`` with the few overrides that do not redefine the run.

    A resumed run must stay the run its config and checkpoint describe: only the budget
    (``agent.iterations``), threads, device, keepaway kernels and logging may change.
    """
    saved = OmegaConf.create(checkpoint["config"])
    values = []
    for item in overrides:
        key, _, value = item.lstrip("+~").partition("=")
        if key == "resume" or key.startswith("hydra"):
            continue
        if key == "logger":
            values.append(f"logger.backend={value}")
            continue
        if key in GROUPS and OmegaConf.select(saved, f"{key}.name", default=None) == value:
            continue
        if key not in RESUMABLE:
            raise ConfigError(
                f"{key}={value} cannot change when resuming (the saved config defines the run); "
                f"allowed: {', '.join(RESUMABLE)}"
            )
        values.append(f"{key}={value}")
    OmegaConf.set_struct(saved, True)
    try:
        merged = OmegaConf.merge(saved, OmegaConf.from_dotlist(values))
    except Exception as exc:  # an override naming a key the saved config lacks
        raise ConfigError(
            f"cannot apply overrides {values} to the resumed run: {str(exc).splitlines()[0]}"
        ) from exc
    merged.resume = str(run_dir)
    return merged


def _commands() -> tuple[str, str]:
    """How to call python and tensorboard as the user can type it (the venv's, if it is not active)."""
    exe = Path(sys.executable)
    board = exe.parent / "tensorboard"
    try:
        rel = exe.relative_to(Path.cwd())
    except ValueError:
        return "python", "tensorboard"
    return str(rel), str(rel.parent / "tensorboard") if board.exists() else "tensorboard"


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


class TrainResult(NamedTuple):
    """Where a run lives and its final score (lines per game of the last evaluation; None if none)."""

    run_dir: Path
    score: float | None


SCORES = ("eval/mean_policy_lines_mean", "eval/lines_per_game_mean", "episode_s_mean")


def train(cfg: DictConfig) -> TrainResult:
    """Train the configured agent; returns the run directory and its final score (a sweeper's objective)."""
    checkpoint = None
    if cfg.resume:
        run_dir = Path(cfg.resume)
        checkpoint = load_checkpoint(run_dir)
        cfg = resume_config(cfg, run_dir, checkpoint, list(HydraConfig.get().overrides.task))
    else:
        run_dir = Path(HydraConfig.get().runtime.output_dir)
    validate_train_config(cfg)
    threads = set_threads(cfg)
    domain, agent = cfg.domain.name, cfg.agent.name
    if checkpoint is not None and (checkpoint["domain"], checkpoint["agent"]) != (domain, agent):
        raise ConfigError(f"resume={str(run_dir)!r} holds a {checkpoint['domain']}/{checkpoint['agent']} run")
    if checkpoint is not None and agent not in SAVES_AS_IT_GOES:
        raise ConfigError(f"agent={agent!r} runs are not resumable (they last seconds); start a new run")
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))

    print(f"Run directory: {run_dir}  ({domain}, {agent}, threads={threads})", file=sys.stderr)
    interrupted = False
    signal.signal(signal.SIGTERM, _interrupt)  # a scheduler's stop ends the run like Ctrl-C
    signal.signal(signal.SIGINT, _interrupt)
    try:
        if agent == "sarsa":
            final = train_sarsa(cfg, run_dir, checkpoint)
        elif agent == "tamer":
            final = train_tamer(cfg, run_dir)
        elif agent == "qlearning":
            final = train_qlearning(cfg, run_dir)
        elif agent == "pg":
            final = train_pg(cfg, run_dir)
        elif cfg.trainer.name == "none":
            final = train_cem(cfg, run_dir, checkpoint)
        else:
            final = train_cem_hf(cfg, run_dir, checkpoint)
    except KeyboardInterrupt:
        interrupted = True
        final = {}
    ckpt = run_dir / "checkpoints" / LAST
    lines = [""]
    if interrupted and agent == "cem":
        lines.append("Interrupted. Every finished iteration is saved; continue with:")
        lines.append(f"  python train.py resume={run_dir}")
    elif interrupted and agent == "sarsa":
        lines.append("Interrupted. Weights and finished episodes are saved (episodes in progress restart);")
        lines.append(f"continue with:  python train.py resume={run_dir}")
    elif interrupted and agent == "tamer":
        lines.append(f"Interrupted. agent={agent} saves its checkpoint at the end, so there is none;")
        lines.append("every feedback event given so far is in feedback.jsonl.")
    elif interrupted:
        lines.append(f"Interrupted. agent={agent} saves its checkpoint at the end, so there is none.")
    elif final and agent == "sarsa":
        low, high = final["episode_s_ci95_low"], final["episode_s_ci95_high"]
        if final["axis"] == "hours" and "sim_seconds" in final:
            window = f"last {cfg.agent.log_minutes:g} simulated minutes"
        elif "episode" in final and final["episode"] > cfg.agent.log_episodes:
            window = f"episodes {final['episode'] - cfg.agent.log_episodes + 1}-{final['episode']}"
        else:
            window = "all its episodes"
        lines.append(
            f"Done: after {final['hours']:.2f} simulated hours per learner ({cfg.agent.learners} learners), "
            f"episodes last {final['episode_s_mean']:.2f} s (95% CI {low:.2f}..{high:.2f}; {window}, "
            "exploring)"
        )
        if "feedback_events" in final:
            who = TRAINER_LABELS.get(cfg.trainer.name, cfg.trainer.name)
            weight = final.get("fusion/weight_mean", 0.0)
            lines.append(
                f"Feedback:         {final['feedback_events']:.0f} events of the {who} "
                f"(fusion={cfg.fusion.name}, mean weight on H^ {weight:.2f})"
            )
            lines.append(f"Feedback log:     {run_dir / 'feedback.jsonl'}")
        lines.append(f"Curves:           {run_dir / 'metrics.jsonl'}")
    elif final and agent == "cem":
        low, high = final["eval/mean_policy_lines_ci95_low"], final["eval/mean_policy_lines_ci95_high"]
        mean = final["eval/mean_policy_lines_mean"]
        lines.append(f"Done: mean policy {mean:.1f} lines per game (95% CI {low:.1f}..{high:.1f})")
    elif final and agent in ("qlearning", "pg"):
        low, high = final["eval/lines_per_game_ci95_low"], final["eval/lines_per_game_ci95_high"]
        mean, game = final["eval/lines_per_game_mean"], final["game"]
        lines.append(
            f"Done: game {game} of {cfg.agent.learners} learners: {mean:.1f} lines per game "
            f"(95% CI {low:.1f}..{high:.1f}) while learning"
        )
        if "eval/greedy_lines_mean" in final:
            g_low, g_high = final["eval/greedy_lines_ci95_low"], final["eval/greedy_lines_ci95_high"]
            lines.append(
                f"Greedy policies:  {final['eval/greedy_lines_mean']:.1f} lines per game over "
                f"{cfg.agent.eval_games} fresh games each (95% CI over learners {g_low:.1f}..{g_high:.1f})"
            )
    elif final:
        low, high = final["eval/lines_per_game_ci95_low"], final["eval/lines_per_game_ci95_high"]
        mean, game = final["eval/lines_per_game_mean"], final["game"]
        who = TRAINER_LABELS.get(cfg.trainer.name, cfg.trainer.name)
        lines.append(
            f"Done: game {game} of {cfg.agent.learners} learners: {mean:.1f} lines per game "
            f"(95% CI {low:.1f}..{high:.1f}), from {final['feedback_events']:.0f} events of the {who}"
        )
        lines.append(f"Feedback log:     {run_dir / 'feedback.jsonl'}")
    python, tensorboard = _commands()
    lines.append(f"Logs and config:  {run_dir}")
    if ckpt.exists():
        lines.append(f"Checkpoint:       {ckpt}")
    if cfg.logger.backend == "tensorboard":
        lines.append(f"TensorBoard:      {tensorboard} --logdir {run_dir / 'tensorboard'}")
    if ckpt.exists():
        keepaway = "domain=keepaway " if domain == "keepaway" else ""
        lines.append(f"Evaluate:         {python} evaluate.py {keepaway}policy={run_dir}")
    print("\n".join(lines), file=sys.stderr)
    if interrupted:
        sys.exit(130)
    score = next((float(final[k]) for k in SCORES if k in final), None) if final else None
    return TrainResult(run_dir, score)
