"""Run a study of many people teaching at once: ``python study.py study=pilot`` (see ``conf/study.yaml`` and
docs/study.md). Running the same command again on the same study directory resumes the study."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import hydra
from hydra.core.global_hydra import GlobalHydra
from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.errors import ConfigError, UserError
from hfrl_torch.experiment.cli import compose_train, guarded, precheck
from hfrl_torch.study.config import StudyConfig
from hfrl_torch.study.manager import Study
from hfrl_torch.study.server import StudyServer

# what every worker runs with besides its condition (study.py sets the port, token and seed itself)
WORKER = ("trainer=interactive",)


@contextlib.contextmanager
def beside_hydra() -> Iterator[None]:
    """Let ``compose_train`` compose ``train`` configs inside ``study.py``'s own Hydra job (Hydra holds one
    global instance: set aside meanwhile, then restored)."""
    instance = GlobalHydra.instance()
    saved = instance.hydra if instance.is_initialized() else None
    instance.clear()
    try:
        yield
    finally:
        instance.clear()
        if saved is not None:
            instance.initialize(saved)


def check_study(cfg: DictConfig) -> tuple[StudyConfig, dict[str, str]]:
    """The study's checked config and each condition's ``human.credit``, every condition composed and checked
    as its workers' ``train.py`` will run it, so that a bad condition fails before anyone joins."""
    study = StudyConfig.from_node(cfg.study)
    credits: dict[str, str] = {}
    for condition in study.conditions:
        try:
            with beside_hydra():
                train = compose_train(*condition.overrides, *study.common, *WORKER)
        except (UserError, ValueError) as exc:
            why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ConfigError(f"study condition {condition.label!r}: {why}") from None
        except Exception as exc:  # Hydra's own errors: an unknown group, key or option
            why = " ".join(str(exc).strip().splitlines()[:1]) or type(exc).__name__
            raise ConfigError(f"study condition {condition.label!r}: {why}") from None
        credits[condition.label] = str(OmegaConf.select(train, "human.credit", default=""))
    return study, credits


def validate_study(cfg: DictConfig) -> None:
    """What :func:`~hfrl_torch.experiment.cli.precheck` runs before Hydra: :func:`check_study`."""
    check_study(cfg)


def wait_for_stop() -> None:
    """Block until Ctrl-C or SIGTERM."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    while not stop.wait(1.0):
        pass


@hydra.main(version_base=None, config_path="conf", config_name="study")
@guarded
def main(cfg: DictConfig) -> None:
    study_cfg, credits = check_study(cfg)
    directory = Path(study_cfg.dir).resolve()
    study = Study.open(study_cfg, directory, python=sys.executable, credits=credits)
    server = StudyServer(
        study, host=study_cfg.host, port=study_cfg.port, allowed_hosts=list(study_cfg.allowed_hosts)
    )
    try:
        server.start()
    except OSError as exc:
        study.close()
        raise UserError(str(exc)) from None
    print(f"study {study_cfg.name!r}: {len(study.overview())} participants so far, kept in {directory}")
    print(f"participants: {server.url}")
    if study_cfg.enrollment == "codes":
        print(f"participant codes (one each): {directory / 'codes.txt'}")
    print(f"researcher (keep this link private): {server.researcher_url}")
    print("serving until Ctrl-C or SIGTERM; running the same command again resumes the study", flush=True)
    try:
        wait_for_stop()
    finally:
        print("stopping: every participant's run saves and stops...", flush=True)
        server.stop()
        study.close()
        print(f"stopped; the study is in {directory}", flush=True)


if __name__ == "__main__":
    precheck(sys.argv[1:], "study", validate_study)
    main()
