"""Entry-point plumbing shared by ``train.py`` and ``evaluate.py``: one-line errors, group checks."""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from pathlib import Path

from hfrl_torch.common.errors import UserError

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"


def check_group_choices(argv: list[str], conf_dir: Path = CONF_DIR) -> None:
    """Exit with one line if a command-line ``group=option`` names an option that does not exist.

    Hydra's own message spans several lines and a hint; this one names the value and the allowed ones.
    """
    for arg in argv:
        if arg.startswith("-") or "=" not in arg:
            continue
        key, _, value = arg.lstrip("+").partition("=")
        group_dir = conf_dir / key
        if "." in key or "/" in key or not group_dir.is_dir():
            continue
        allowed = sorted(p.stem for p in group_dir.glob("*.yaml"))
        for choice in value.split(","):  # a multirun sweep lists several
            if choice not in allowed:
                fail(f"unknown {key} {choice!r}; allowed: {', '.join(allowed)}")


DOMAIN_DEFAULTS = {"keepaway": {"agent": "sarsa", "human": "tile_coded"}}


def implied_overrides(argv: list[str]) -> list[str]:
    """Group choices a command line implies but does not name: a domain's own learner and H^
    (``domain=keepaway``: ``agent=sarsa human=tile_coded``), the simulated oracle for a fusion that
    needs a trainer (``fusion=linear``: ``trainer=oracle``), and one team of keepers for a person
    (``domain=keepaway trainer=interactive``: ``agent.learners=1``). Sweeps over a group are left alone."""
    given: dict[str, str] = {}
    for arg in argv:
        if not arg.startswith("-") and "=" in arg:
            key, _, value = arg.lstrip("+~").partition("=")
            given[key] = value
    if "resume" in given and given["resume"] not in ("", "null"):
        return []
    extra: dict[str, str] = {}
    for group, choice in DOMAIN_DEFAULTS.get(given.get("domain", ""), {}).items():
        if group not in given:
            extra[group] = choice
    fusion = given.get("fusion", "none")
    if "," not in fusion and fusion != "none" and "trainer" not in given and "experiment" not in given:
        extra["trainer"] = "oracle"
    person = given.get("domain") == "keepaway" and given.get("trainer") == "interactive"
    if person and "agent.learners" not in given:
        extra["agent.learners"] = "1"
    return [f"{k}={v}" for k, v in extra.items()]


def resume_log_dir(argv: list[str]) -> list[str]:
    """Extra overrides that keep a resume invocation's Hydra files inside the resumed run."""
    resume = [a.partition("=")[2] for a in argv if a.startswith("resume=")]
    if not resume or not resume[-1] or any(a.startswith("hydra.run.dir=") for a in argv):
        return []
    return [f"hydra.run.dir={resume[-1]}/resume-logs/${{now:%Y-%m-%d_%H-%M-%S}}"]


def check_overrides(
    argv: list[str],
    config_name: str,
    validate: Callable[[object], None] | None = None,
    conf_dir: Path = CONF_DIR,
) -> None:
    """Compose the config once up front so that a bad override fails with one line (not Hydra's
    page) and before Hydra creates a run directory; ``validate`` checks the values.

    Sweeps (``-m``) are left to Hydra: their values are checked by each job.
    """
    check_group_choices(argv, conf_dir)
    if any(a in ("-m", "--multirun") for a in argv):
        return
    overrides = [a for a in argv if not a.startswith("-") and not a.lstrip("+~").startswith("hydra")]
    from hydra import compose, initialize_config_dir

    try:
        with initialize_config_dir(str(conf_dir), version_base=None):
            cfg = compose(config_name, overrides=overrides)
    except Exception as exc:  # Hydra raises several types; all mean the command line is wrong
        fail(" ".join(str(exc).strip().splitlines()[:2]) or type(exc).__name__)
    if validate is not None and not cfg.get("resume"):
        try:
            validate(cfg)
        except (UserError, ValueError) as exc:
            fail(str(exc).splitlines()[0])


def fail(message: str) -> None:
    """Print ``error: message`` on stderr and exit with status 2."""
    print(f"error: {message}", file=sys.stderr)
    sys.exit(2)


def guarded(fn: Callable[..., object]) -> Callable[..., object]:
    """Run ``fn`` turning a :class:`UserError` into one ``error:`` line and exit status 2."""

    @functools.wraps(fn)
    def wrapper(*args: object, **kwargs: object) -> object:
        try:
            return fn(*args, **kwargs)
        except UserError as exc:
            fail(str(exc))
        except ValueError as exc:  # invalid values caught by constructors (rules, feature sets)
            if "\n" in str(exc) or not str(exc):
                raise
            fail(str(exc))
        return None

    return wrapper
