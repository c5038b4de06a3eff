"""Experiment logging: TensorBoard scalars, text and images, or nothing (``logger.backend=none``)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


class Logger:
    """A no-op logger; :class:`TensorBoardLogger` writes what this one drops."""

    log_dir: Path | None = None

    def scalar(self, tag: str, value: float, step: int) -> None:
        """Record one scalar."""

    def scalars(self, values: dict[str, float], step: int, prefix: str = "") -> None:
        """Record several scalars under ``prefix``."""
        for k, v in values.items():
            self.scalar(f"{prefix}{k}", float(v), step)

    def text(self, tag: str, text: str, step: int = 0) -> None:
        """Record a markdown text (e.g. the hyper-parameters)."""

    def image(self, tag: str, image: np.ndarray, step: int) -> None:
        """Record an [H, W, 3] uint8 image."""

    def hparams(self, hparams: dict[str, Any], metrics: dict[str, float]) -> None:
        """Record the run's hyper-parameters with its final metrics (TensorBoard's HPARAMS view)."""

    def flush(self) -> None:
        """Write buffered events."""

    def close(self) -> None:
        """Flush and close."""


class TensorBoardLogger(Logger):
    """Writes TensorBoard event files into ``log_dir``; ``purge_step`` drops events of an interrupted run."""

    def __init__(self, log_dir: str | Path, purge_step: int | None = None) -> None:
        from torch.utils.tensorboard import SummaryWriter

        self.log_dir = Path(log_dir)
        self._writer = SummaryWriter(log_dir=str(self.log_dir), purge_step=purge_step)

    def scalar(self, tag: str, value: float, step: int) -> None:
        self._writer.add_scalar(tag, value, step)

    def text(self, tag: str, text: str, step: int = 0) -> None:
        self._writer.add_text(tag, text, step)

    def image(self, tag: str, image: np.ndarray, step: int) -> None:
        self._writer.add_image(tag, image, step, dataformats="HWC")

    def hparams(self, hparams: dict[str, Any], metrics: dict[str, float]) -> None:
        clean = {k: v if isinstance(v, (int, float, str, bool)) else str(v) for k, v in hparams.items()}
        self._writer.add_hparams(clean, metrics, run_name=".")

    def flush(self) -> None:
        self._writer.flush()

    def close(self) -> None:
        self._writer.close()


BACKENDS = ("tensorboard", "none")


def make_logger(backend: str, log_dir: str | Path, purge_step: int | None = None) -> Logger:
    """The logger named ``backend`` writing under ``log_dir``."""
    if backend == "tensorboard":
        return TensorBoardLogger(log_dir, purge_step=purge_step)
    if backend == "none":
        return Logger()
    raise ValueError(f"logger.backend={backend!r} is invalid; allowed: {', '.join(BACKENDS)}")


def flatten_config(cfg: Any) -> dict[str, object]:
    """A resolved OmegaConf config as ``{"agent.population": 100, ...}`` (for hparams tables)."""
    from omegaconf import OmegaConf

    out: dict[str, object] = {}

    def walk(node: object, prefix: str) -> None:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}.")
        else:
            out[prefix.rstrip(".")] = node

    walk(OmegaConf.to_container(cfg, resolve=True), "")
    return out


def markdown_table(values: dict[str, Any]) -> str:
    """A two-column markdown table of parameters, as CleanRL writes its hyper-parameters."""
    rows = "\n".join(f"|{k}|{v}|" for k, v in values.items())
    return f"|param|value|\n|-|-|\n{rows}"
