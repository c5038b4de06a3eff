"""Checks of config values that fail with one line naming the value and what is allowed."""

from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.errors import ConfigError


def _get(cfg: DictConfig, path: str) -> Any:
    value = OmegaConf.select(cfg, path, throw_on_missing=False)
    if value is None:
        raise ConfigError(f"{path} is missing from the config")
    return value


def require_int(cfg: DictConfig, path: str, low: int | None = None, high: int | None = None) -> int:
    """The integer at ``path``, within [low, high]."""
    value = _get(cfg, path)
    ok = isinstance(value, int) and not isinstance(value, bool)
    ok = ok and (low is None or value >= low) and (high is None or value <= high)
    if not ok:
        raise ConfigError(f"{path}={value!r} is invalid: must be an integer {_range(low, high)}")
    return value


def require_float(cfg: DictConfig, path: str, low: float | None = None, high: float | None = None) -> float:
    """The number at ``path``, within [low, high]."""
    value = _get(cfg, path)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (low is None or value >= low) and (high is None or value <= high)
    if not ok:
        raise ConfigError(
            f"{path}={value!r} is invalid: must be a finite number {_range(low, high)}".rstrip()
        )
    return float(value)


def require_choice(cfg: DictConfig, path: str, allowed: Iterable[str]) -> str:
    """The string at ``path``, one of ``allowed``."""
    value = _get(cfg, path)
    allowed = list(allowed)
    if value not in allowed:
        raise ConfigError(f"{path}={value!r} is invalid; allowed: {', '.join(map(str, allowed))}")
    return value


def require_bool(cfg: DictConfig, path: str) -> bool:
    """The boolean at ``path``."""
    value = _get(cfg, path)
    if not isinstance(value, bool):
        raise ConfigError(f"{path}={value!r} is invalid: must be true or false")
    return value


def _range(low: float | None, high: float | None) -> str:
    if low is not None and high is not None:
        return f"in {low}..{high}"
    if low is not None:
        return f">= {low}"
    if high is not None:
        return f"<= {high}"
    return ""
