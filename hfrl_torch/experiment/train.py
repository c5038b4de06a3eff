"""What ``train.py`` does: set up (or resume) a run directory, run the agent's learner, say where it is."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path
from typing import Any, NamedTuple

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError, UserError
from hfrl_torch.experiment.cli import checked
from hfrl_torch.experiment.config import resume_config, validate_train
from hfrl_torch.experiment.factories import set_threads
from hfrl_torch.experiment.registry import learner_for
from hfrl_torch.experiment.run import Interrupt, RunFiles, learn
from hfrl_torch.fusion.weights import UNWEIGHTED

EVALUATE_DEFAULT_DOMAIN = "tetris"  # conf/evaluate.yaml's default domain
SIMULATED = ("oracle", "value_proxy", "replay")  # trainers a comparison sweep can run again without a person


class TrainResult(NamedTuple):
    """Where a run lives and its final score (a sweeper's objective; None if there is none)."""

    run_dir: Path
    score: float | None


def _compare_lines(cfg: DictConfig, python: str, overrides: list[str]) -> list[str]:
    """The two commands that run this fused run's parts beside it (the environment alone, H^ alone where the
    agent has that condition) and compare them: a fused run's number means little on its own."""
    name = str(cfg.fusion.name)
    if name in UNWEIGHTED or str(cfg.trainer.name) not in SIMULATED:
        return []
    parts = [p for p in UNWEIGHTED if _valid_with(cfg, p)]
    kept = [o for o in overrides if not o.lstrip("+~").startswith(("fusion=", "hydra.", "resume="))]
    where = f"multirun/compare_{cfg.domain.name}_{cfg.agent.name}_{name}"
    sweep = " ".join(shlex.quote(o) for o in [*kept, f"fusion={','.join([*parts, name])}"])
    return [
        f"Compare:          {python} train.py -m {sweep} hydra.sweep.dir={where}",
        f"                  {python} evaluate.py runs={where}   "
        f"(the same run beside {' and '.join(parts)}, paired)",
    ]


def _config_dir_args(sources: Any) -> list[str]:
    """``--config-dir <dir>`` for each config directory the user named (Hydra's ``runtime.config_sources``
    from the command line), so that a printed command finds the user's own options as this run did."""
    return [a for s in sources if s.provider == "command-line" for a in ("--config-dir", str(s.path))]


def _valid_with(cfg: DictConfig, fusion: str) -> bool:
    """Whether this run's config is valid with ``fusion=<fusion>`` in place of its own scheme."""
    other = cfg.copy()
    OmegaConf.set_struct(other, False)
    other.fusion.name = fusion
    try:
        validate_train(other)
    except (UserError, ValueError):
        return False
    return True


def _commands() -> tuple[str, str]:
    """How to call python and tensorboard as the user can type it (the venv's, if it is not active)."""
    exe = Path(sys.executable)
    board = exe.parent / "tensorboard"
    try:
        rel = exe.relative_to(Path.cwd())
    except ValueError:
        return "python", "tensorboard"
    return str(rel), str(rel.parent / "tensorboard") if board.exists() else "tensorboard"


def train(cfg: DictConfig) -> TrainResult:
    """Train the configured agent; returns the run directory and its final score."""
    checkpoint = None
    if cfg.resume:
        run_dir = Path(cfg.resume)
        checkpoint = load_checkpoint(run_dir)
        cfg = resume_config(cfg, run_dir, checkpoint, list(HydraConfig.get().overrides.task))
    else:
        run_dir = Path(HydraConfig.get().runtime.output_dir)
    if not checked():  # a job nobody checked up front (a sampling sweeper's): check it here
        validate_train(cfg)
    threads = set_threads(cfg)
    domain, agent = cfg.domain.name, cfg.agent.name
    if checkpoint is not None and (checkpoint["domain"], checkpoint["agent"]) != (domain, agent):
        raise ConfigError(f"resume={str(run_dir)!r} holds a {checkpoint['domain']}/{checkpoint['agent']} run")
    (run_dir / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))

    print(f"Run directory: {run_dir}  ({domain}, {agent}, threads={threads})", file=sys.stderr)
    choices = " ".join(f"{g}={cfg[g].name}" for g in ("domain", "agent", "human", "fusion", "trainer"))
    print(f"Choices: {choices}", file=sys.stderr)
    learner = learner_for(agent, domain)(cfg, run_dir, checkpoint)
    files = RunFiles(run_dir, cfg)
    interrupt = Interrupt()
    interrupt.install()
    try:
        final = learn(learner, files, interrupt=interrupt)
    except KeyboardInterrupt:
        print(
            f"\nInterrupted. Everything up to the last checkpoint is saved; continue with:\n"
            f"  python train.py resume={run_dir}",
            file=sys.stderr,
        )
        sys.exit(130)
    python, tensorboard = _commands()
    lines = ["", *(learner.report(final) if final else [])]
    if final:
        lines.append(f"Curves:           {files.metrics}")
    lines.append(f"Logs and config:  {run_dir}")
    if files.checkpoint.exists():
        lines.append(f"Checkpoint:       {files.checkpoint}")
    if cfg.logger.backend == "tensorboard":
        lines.append(f"TensorBoard:      {tensorboard} --logdir {run_dir / 'tensorboard'}")
    if files.checkpoint.exists():
        choice = "" if domain == EVALUATE_DEFAULT_DOMAIN else f"domain={domain} "
        lines.append(f"Evaluate:         {python} evaluate.py {choice}policy={run_dir}")
    if final and not cfg.resume:
        hydra = HydraConfig.get()
        own = _config_dir_args(hydra.runtime.config_sources)
        lines += _compare_lines(cfg, python, [*own, *hydra.overrides.task])
    print("\n".join(lines), file=sys.stderr)
    return TrainResult(run_dir, learner.score(final) if final else None)
