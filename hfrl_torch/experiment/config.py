"""Every check of a run's config, run once before anything is written.

``train.py`` and ``evaluate.py`` call :func:`validate_train` / :func:`validate_evaluate` on each job's
composed config before Hydra makes a run directory (``app.precheck``), so a bad value stops the run with one
line naming the value and what is allowed. They dispatch through the registry: the domain checks its group
(``Domain.check``), the learner its agent, H^ and trainer (``Learner.check``), and the fusion weight is
checked for what that learner gives it. The ``make_*`` factories then build from a config that is known to
be good, and check nothing themselves.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.logger import BACKENDS
from hfrl_torch.common.validation import require_choice, require_int
from hfrl_torch.experiment.checks import TRAINERS, check_device, check_fusion, check_threads
from hfrl_torch.experiment.registry import agent_names, domain_for, evidence_givers, learner_for
from hfrl_torch.fusion.schemes import FUSIONS

RESUMABLE = (
    "agent.iterations",
    "agent.hours",
    "agent.episodes",
    "agent.games",
    "agent.frames",  # the DQN learners' budget (the browser trainer's summary offers more of it)
    "threads",
    "device",
    "domain.kernels",
    "agent.kernels",
    "logger.backend",
    "trainer.port",  # where the page is served, and its token, do not change what the run learns
    "trainer.token",
    "trainer.blind",  # what the page is shown of the condition, not what the run learns
)
# resumable settings added after some runs were saved: (the group option that has it, what such a run had),
# so that a resume may set them on an older run too
LATER_DEFAULTS: dict[str, tuple[str, Any]] = {"trainer.blind": ("interactive", False)}
GROUPS = ("domain", "agent", "fusion", "human", "trainer", "logger")


def validate_train(cfg: DictConfig) -> None:
    """Check every value ``train.py`` uses; raises ``ConfigError`` with one line on the first bad one."""
    require_int(cfg, "seed", 0, 2**62)
    domain = domain_for(cfg)
    agent = require_choice(cfg, "agent.name", agent_names())
    require_choice(cfg, "fusion.name", FUSIONS)
    require_choice(cfg, "trainer.name", TRAINERS)
    require_choice(cfg, "logger.backend", BACKENDS)
    check_threads(cfg)
    check_device(cfg)
    learner = learner_for(agent, domain.name)
    domain.check(cfg)
    learner.check(cfg)
    check_fusion(cfg, learner.weight_evidence, evidence_givers(), spread=domain.spread)


def validate_evaluate(cfg: DictConfig) -> None:
    """Check what ``evaluate.py`` uses before it plays (a checkpoint's own task is checked when it loads)."""
    if cfg.get("runs") is not None:
        return  # the report checks its own options (aggregate.py)
    require_int(cfg, "seed", 0, 2**62)
    check_threads(cfg)
    domain_for(cfg).check_evaluate(cfg)


def resume_config(
    cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any], overrides: list[str]
) -> DictConfig:
    """The saved config of ``run_dir`` with the few overrides that do not redefine the run.

    A resumed run must stay the run its config and checkpoint describe: only the budget, threads, device,
    keepaway kernels and logging may change.
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
    for key, (option, default) in LATER_DEFAULTS.items():
        group, _, name = key.rpartition(".")
        node = OmegaConf.select(saved, group)
        if isinstance(node, DictConfig) and node.get("name") == option and name not in node:
            node[name] = default
    OmegaConf.set_struct(saved, True)
    try:
        merged = OmegaConf.merge(saved, OmegaConf.from_dotlist(values))
    except Exception as exc:  # an override naming a key the saved config lacks
        raise ConfigError(
            f"cannot apply overrides {values} to the resumed run: {str(exc).splitlines()[0]}"
        ) from exc
    merged.resume = str(run_dir)
    return merged
