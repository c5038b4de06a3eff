"""``make_*`` factories from the Hydra config, each checking its own section first.

Every bad value raises :class:`ConfigError` naming the value and what is allowed,
before any work starts.
"""

from __future__ import annotations

import re

import numba
import torch
from omegaconf import DictConfig

from hfrl_torch.agents.cem import CEMConfig
from hfrl_torch.agents.cem.cem import NOISE_SCHEDULES, Rollout
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.logger import BACKENDS, Logger, make_logger
from hfrl_torch.common.validation import require_bool, require_choice, require_float, require_int
from hfrl_torch.envs.tetris.env import ENGINES, TetrisEnv
from hfrl_torch.envs.tetris.features import feature_id
from hfrl_torch.envs.tetris.rules import TetrisRules

DOMAINS = ("tetris",)
AGENTS = ("cem",)
FUSIONS = ("none",)
TRAINERS = ("none",)
FEATURE_SETS = ("bt", "knox", "dellacherie", "dt")


def make_device(cfg: DictConfig) -> torch.device:
    """The torch device named by ``device`` (``cpu``, ``cuda``, ``cuda:N``)."""
    name = cfg.device
    if not isinstance(name, str) or not re.fullmatch(r"cpu|cuda(:\d+)?", name):
        raise ConfigError(f"device={name!r} is invalid; allowed: cpu, cuda, cuda:N")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={name!r} was asked for but no CUDA device is available; use device=cpu")
    return torch.device(name)


def set_threads(cfg: DictConfig) -> int:
    """Apply ``threads`` to torch and numba (the engines' games run in parallel over threads)."""
    n = require_int(cfg, "threads", 1, 256)
    n = min(n, numba.config.NUMBA_NUM_THREADS)
    torch.set_num_threads(n)
    numba.set_num_threads(n)
    return n


def make_rules(cfg: DictConfig) -> TetrisRules:
    """Tetris rules from ``domain``."""
    require_choice(cfg, "domain.name", DOMAINS)
    return TetrisRules(
        width=require_int(cfg, "domain.width", 4, 30),
        height=require_int(cfg, "domain.height", 4, 1000),
        bag=require_bool(cfg, "domain.bag"),
        spawn_topout=require_bool(cfg, "domain.spawn_topout"),
        preview=require_bool(cfg, "domain.preview"),
    )


def check_domain(cfg: DictConfig) -> None:
    """Check the domain's non-rule settings."""
    require_choice(cfg, "domain.features", FEATURE_SETS)
    require_choice(cfg, "domain.engine", ENGINES)
    require_int(cfg, "domain.max_pieces", 0)


def make_env(cfg: DictConfig, batch: int) -> TetrisEnv:
    """A batched ``TetrisEnv`` from ``domain`` and ``device``."""
    check_domain(cfg)
    return TetrisEnv(
        batch=batch,
        rules=make_rules(cfg),
        features=cfg.domain.features,
        engine=cfg.domain.engine,
        max_pieces=cfg.domain.max_pieces,
        device=make_device(cfg),
        seed=cfg.seed,
    )


def make_rollout(cfg: DictConfig, features: str | None = None) -> Rollout:
    """Whole-game rollouts of linear policies on the configured engine (numba on CPU)."""
    check_domain(cfg)
    rules = make_rules(cfg)
    fid = feature_id(features or cfg.domain.features)
    device = make_device(cfg)
    engine = cfg.domain.engine
    if engine == "auto":
        engine = "numba" if device.type == "cpu" else "torch"
    max_pieces = cfg.domain.max_pieces

    if engine == "numba":
        if device.type != "cpu":
            raise ConfigError(f"domain.engine='numba' runs on the CPU only, not on device={device}")
        from hfrl_torch.envs.tetris.engine_numba import play
    else:
        from hfrl_torch.envs.tetris import engine_torch

        def play(*args, **kwargs):
            return engine_torch.play(*args, device=device, **kwargs)

    def rollout(weights: torch.Tensor, seeds: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        lines, pieces, _ = play(rules, fid, weights, seeds, max_pieces=max_pieces)
        return lines.cpu(), pieces.cpu()

    return rollout


def make_cem_config(cfg: DictConfig) -> CEMConfig:
    """CE settings from ``agent``."""
    require_choice(cfg, "agent.name", AGENTS)
    require_int(cfg, "agent.iterations", 1)
    return CEMConfig(
        population=require_int(cfg, "agent.population", 2),
        elite_fraction=require_float(cfg, "agent.elite_fraction", 0.001, 1.0),
        initial_mean=require_float(cfg, "agent.initial_mean"),
        initial_variance=require_float(cfg, "agent.initial_variance", 0.0),
        noise=require_choice(cfg, "agent.noise", NOISE_SCHEDULES),
        noise_value=require_float(cfg, "agent.noise_value", 0.0),
        noise_start=require_float(cfg, "agent.noise_start", 0.0),
        noise_decay=require_float(cfg, "agent.noise_decay", 1e-9),
        games_per_candidate=require_int(cfg, "agent.games_per_candidate", 1),
        eval_games=require_int(cfg, "agent.eval_games", 1),
    )


def check_run(cfg: DictConfig) -> None:
    """Check the top-level and the not-yet-implemented groups."""
    require_int(cfg, "seed", 0, 2**62)
    require_choice(cfg, "fusion.name", FUSIONS)
    require_choice(cfg, "trainer.name", TRAINERS)
    require_choice(cfg, "logger.backend", BACKENDS)
    make_device(cfg)


def make_run_logger(cfg: DictConfig, log_dir: str, purge_step: int | None) -> Logger:
    """The logger of ``logger.backend`` writing under ``log_dir``."""
    return make_logger(cfg.logger.backend, log_dir, purge_step=purge_step)


def validate_train_config(cfg: DictConfig) -> None:
    """Check every section ``train.py`` uses, before any work or output."""
    if cfg.domain.name != "tetris":
        raise ConfigError(
            f"domain={cfg.domain.name!r} has no learning agent yet; trainable: tetris "
            f"(evaluate its benchmark policies: python evaluate.py domain={cfg.domain.name} policy=hand)"
        )
    check_run(cfg)
    make_rules(cfg)
    check_domain(cfg)
    make_cem_config(cfg)
    require_int(cfg, "threads", 1, 256)
