"""``module:callable`` names in a config (a user's env factory, a reference policy), imported with one-line
errors; the directory the user ran the command in is searched too, so their own modules import."""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Callable
from typing import Any

from hfrl_torch.common.errors import ConfigError

__all__ = ["load_callable"]


def load_callable(spec: object, key: str) -> Callable[..., Any]:
    """The callable ``spec`` (``"package.module:name"``) names; ``ConfigError`` naming ``key`` otherwise."""
    if not isinstance(spec, str) or spec.count(":") != 1 or not all(spec.split(":")):
        raise ConfigError(f"{key}={spec!r} is invalid: must be 'package.module:callable'")
    module_name, _, attr = spec.partition(":")
    here = os.getcwd()
    if here not in sys.path:
        sys.path.append(here)  # the user's own modules, next to where they ran train.py
    try:
        module = importlib.import_module(module_name)
    except Exception as exc:  # a user's module may fail in any way while importing
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"{key}={spec!r} does not import: {first}") from None
    target: Any = module
    for part in attr.split("."):
        if not hasattr(target, part):
            raise ConfigError(f"{key}={spec!r} is invalid: {module_name} has no {attr!r}")
        target = getattr(target, part)
    if not callable(target):
        raise ConfigError(f"{key}={spec!r} is invalid: {attr} is a {type(target).__name__}, not a callable")
    return target
