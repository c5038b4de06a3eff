"""What ``train.py`` and ``evaluate.py`` do before Hydra runs: check every job's config, with one-line errors.

Hydra's own command line is left as Hydra parses it (``--cfg job|hydra|all``, ``--resolve``, ``--package``,
``--info``, ``--help``, ``-m``): :func:`precheck` reads it with Hydra's own argument parser, composes the
config of every job a command would run (each combination of a basic sweep, the sweeps an experiment config
declares included) and validates each before Hydra creates a directory. A bad value stops the command with
``error: <one line>`` and exit status 2, and nothing is written.
"""

from __future__ import annotations

import functools
import os
import sys
from collections.abc import Callable
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra._internal.utils import get_args_parser
from hydra.core.hydra_config import HydraConfig
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import UserError
from hfrl_torch.experiment import resolvers  # noqa: F401  (the config's resolvers, before any composing)
from hfrl_torch.experiment.config import resume_config, validate_train
from hfrl_torch.fusion.weights import WEIGHT_UNUSED

CONF_DIR = Path(__file__).resolve().parent.parent.parent / "conf"
CHECKED = "HFRL_TORCH_CHECKED"  # set once every job of this command was checked up front
_HYDRA_FLAGS = ("help", "hydra_help", "version", "cfg", "info", "shell_completion", "experimental_rerun")


def check_group_choices(overrides: list[str], conf_dirs: tuple[Path, ...] = (CONF_DIR,)) -> None:
    """Exit with one line if a ``group=option`` names an option that does not exist in any of ``conf_dirs``
    (Hydra's own message spans several lines and a hint; this one names the value and the allowed ones)."""
    for arg in overrides:
        if "=" not in arg:
            continue
        key, _, value = arg.lstrip("+~").partition("=")
        group_dirs = [d / key for d in conf_dirs if (d / key).is_dir()]
        if "." in key or "/" in key or not group_dirs:
            continue
        names = sorted({p.stem for d in group_dirs for p in d.glob("*.yaml")})
        shown = [n for n in names if not n.startswith("default_")]
        for choice in value.split(","):  # a sweep lists several
            if choice not in names:
                fail(f"unknown {key} {choice!r}; allowed: {', '.join(shown)}")


def job_overrides(overrides: list[str], config_name: str, multirun: bool) -> tuple[list[list[str]], bool]:
    """The overrides of every job the command runs, and whether that is all of them: one job, or each
    combination of a basic sweep (the command line's and the ``hydra.sweeper.params`` of the composed
    config); a sampling sweeper (Optuna) is represented by its base job, its sampled values being checked by
    each job itself."""
    if not multirun:
        return [overrides], True
    parser = OverridesParser.create()
    parsed = parser.parse_overrides(overrides)
    base = [o.input_line for o in parsed if not o.is_sweep_override()]
    hydra_cfg = compose_config(config_name, *base, hydra=True).hydra
    if not str(OmegaConf.select(hydra_cfg, "sweeper._target_", default="")).endswith("BasicSweeper"):
        return [base], False
    params = OmegaConf.select(hydra_cfg, "sweeper.params", default=None) or {}
    declared = [f"{k}={v}" for k, v in params.items()]
    return BasicSweeper.split_arguments(parser.parse_overrides(declared + overrides), None)[0], True


def _job_dir(hydra: DictConfig, index: int | None) -> Path | None:
    """The directory a job will write to (a single run's ``hydra.run.dir``, a sweep job's
    ``hydra.sweep.dir/<subdir>``); None for ``evaluate.py``, which writes none."""
    if hydra.get("output_subdir") is None:
        return None
    if index is None:
        return Path(str(hydra.run.dir))
    subdir = str(OmegaConf.to_container(hydra.sweep, resolve=False).get("subdir", ""))
    return Path(str(hydra.sweep.dir)) / subdir.replace("${hydra.job.num}", str(index))


def check_fresh(path: Path | None, resuming: bool) -> None:
    """Refuse to start a new run in a directory that already holds one (resume it, or choose another)."""
    if path is None or resuming or not (path / "config.yaml").exists():
        return
    raise UserError(
        f"{path} already holds a run; resume it with resume={path}, or choose another directory "
        "(hydra.run.dir, or hydra.sweep.dir for a sweep)"
    )


def compose_config(config_name: str, *overrides: str, hydra: bool = False) -> DictConfig:
    """The config ``config_name`` (``train`` or ``evaluate``) composed from ``conf/`` with ``overrides``,
    unchecked; with ``hydra`` Hydra's own config under ``hydra`` too, otherwise ``hydra.*`` overrides are
    left out. The one composing helper of the package, its tests and benchmarks."""
    task = list(overrides) if hydra else [o for o in overrides if not o.lstrip("+~").startswith("hydra")]
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        return compose(config_name, overrides=task, return_hydra_config=hydra)


def compose_train(*overrides: str) -> DictConfig:
    """The composed and checked ``train`` config of ``overrides``, as ``train.py`` would run it."""
    cfg = compose_config("train", *overrides)
    validate_train(cfg)
    return cfg


def _split(config_name: str, overrides: list[str]) -> tuple[DictConfig, DictConfig]:
    """The job's config and Hydra's, from one composition (composing is most of a check's cost)."""
    full = compose_config(config_name, *overrides, hydra=True)
    cfg = OmegaConf.masked_copy(full, [k for k in full if k != "hydra"])
    OmegaConf.set_struct(cfg, True)
    return cfg, full.hydra


def precheck(argv: list[str], config_name: str, validate: Callable[[DictConfig], None]) -> None:
    """Check every job of this command line before Hydra runs it (see the module docstring)."""
    try:
        args = get_args_parser().parse_args(argv)
    except SystemExit:
        return  # a malformed command line: Hydra says what is wrong with it
    if any(getattr(args, flag, None) for flag in _HYDRA_FLAGS):
        return  # Hydra's own flags print or inspect the config; they run nothing
    overrides, conf_dirs, added = list(args.overrides), (CONF_DIR,), ""
    if args.config_dir:  # --config-dir: the user's own groups and options, searched as Hydra will
        user = Path(args.config_dir).expanduser().resolve()
        added = f"hydra.searchpath=[file://{user}]"
        overrides.append(added)
        conf_dirs = (CONF_DIR, user)

    def shown(job: list[str]) -> str:
        return " ".join(o for o in job if o != added)

    check_group_choices(args.overrides, conf_dirs)
    try:
        jobs, complete = job_overrides(overrides, config_name, bool(args.multirun))
        runs: dict[str, int] = {}
        for i, job in enumerate(jobs):
            cfg, hydra = _split(config_name, job)
            same = runs.setdefault(_run_key(cfg), i)
            if same != i:
                fail(
                    f"jobs {same} ({shown(jobs[same])}) and {i} ({shown(job)}) are the same run"
                    f"{_why_same(cfg)}: a sweep of duplicates counts one learner twice; sweep the setting "
                    "in its own command over the options it changes"
                )
            resuming = bool(cfg.get("resume"))
            if resuming:
                checkpoint = load_checkpoint(cfg.resume)
                cfg = resume_config(cfg, Path(cfg.resume), checkpoint, job)
            try:
                validate(cfg)
                check_fresh(_job_dir(hydra, i if args.multirun else None), resuming)
            except (UserError, ValueError) as exc:
                where = f"job {i} ({shown(job)}): " if len(jobs) > 1 else ""
                fail(where + str(exc).splitlines()[0])
    except UserError as exc:
        fail(str(exc).splitlines()[0])
    except Exception as exc:  # Hydra raises several types; all mean the command line is wrong
        fail(" ".join(str(exc).strip().splitlines()[:2]) or type(exc).__name__)
    if complete:  # every job the launcher will run was checked here
        os.environ[CHECKED] = "1"


def _run_key(cfg: DictConfig) -> str:
    """What defines a run: the job's config, less the settings its choices leave unused (the weight of a
    scheme that fuses nothing)."""
    copy = OmegaConf.to_container(cfg, resolve=False)
    fusion = copy.get("fusion") if isinstance(copy, dict) else None
    if isinstance(fusion, dict) and fusion.get("name") in WEIGHT_UNUSED:
        fusion.pop("weight", None)
    return OmegaConf.to_yaml(OmegaConf.create(copy))


def _why_same(cfg: DictConfig) -> str:
    name = OmegaConf.select(cfg, "fusion.name", default=None)
    return f" (fusion={name} uses no fusion.weight)" if name in WEIGHT_UNUSED else ""


def checked() -> bool:
    """Whether this command's jobs were checked up front (else the job checks its own config)."""
    return os.environ.get(CHECKED) == "1"


def fail(message: str) -> None:
    """Print ``error: message`` on stderr and exit with status 2."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


class JobFailed(RuntimeError):
    """A sweep job stopped on bad input: reported as its one line, and the sweep goes on."""


def guarded(fn: Callable[..., object]) -> Callable[..., object]:
    """Run ``fn`` turning a :class:`UserError` into one ``error:`` line: exit status 2 for a single run; in a
    sweep, a failed job (Hydra reports it and runs the next jobs, and the sweep ends with status 1)."""

    @functools.wraps(fn)
    def wrapper(*args: object, **kwargs: object) -> object:
        try:
            return fn(*args, **kwargs)
        except UserError as exc:
            message = str(exc)
        except ValueError as exc:  # invalid values caught by constructors (rules, feature sets)
            if "\n" in str(exc) or not str(exc):
                raise
            message = str(exc)
        _fail_job(message)
        return None

    return wrapper


def _fail_job(message: str) -> None:
    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        print(f"error: {message}", file=sys.stderr)
        raise JobFailed(message)
    fail(message)
