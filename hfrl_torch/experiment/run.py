"""The one shape of a training run: a learner advanced chunk by chunk, and what the run writes as it goes.

Every learner (``experiment/learners/``) is a :class:`Learner`: built from the config (and the checkpoint
it resumes), advanced by :meth:`Learner.advance`, which returns the points of the learning curve it closed.
:func:`learn` is the loop around it, written once, like Stable-Baselines3's ``learn()``: a progress bar,
every point to TensorBoard and ``metrics.jsonl``, a checkpoint whenever the learner says one is due and at
the end, and :class:`Callback` hooks. The curve lives in the checkpoint too: a resumed run rewrites
``metrics.jsonl`` from it, so a kill between a checkpoint and the next line loses nothing and duplicates
nothing, and TensorBoard drops the events written after the checkpoint.

Stopping (:class:`Interrupt`): Ctrl-C or SIGTERM during a chunk lets the chunk finish, saves a checkpoint
and stops; a second one, or one outside a chunk (a learner waiting for its page), stops at once and keeps
the last checkpoint written, never a half-learned state. The learner is told at once
(:meth:`Learner.interrupted`), so that it can end its chunk sooner (the browser trainer stops pacing its
game). A learner can also ask to finish early (:attr:`Learner.stop_requested`: the browser trainer's
"Finish and save"): the run then ends after the chunk like one that reached its budget, with a checkpoint.
"""

from __future__ import annotations

import atexit
import gc
import json
import os
import signal
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.logger import Logger, flatten_config, make_logger, markdown_table

if TYPE_CHECKING:  # the page's server, only named in annotations
    from hfrl_torch.interactive.live import LiveTeaching

__all__ = ["Callback", "Interrupt", "Learner", "Point", "RunFiles", "learn"]


class Interrupt:
    """Ctrl-C and SIGTERM for :func:`learn`: deferred to the end of the chunk in progress, once."""

    def __init__(self) -> None:
        self.requested = False
        self.deferring = False
        self.notify: Callable[[], None] | None = None  # told of a deferred stop (from the signal handler)

    def install(self) -> None:
        """Handle SIGINT and SIGTERM (a scheduler's stop ends the run like Ctrl-C), in a process that ends
        with its run (``train.py``): its exit then skips the collector's passes over every object the
        imports made (about 2 s of a 2-core machine; the run's files are closed by then)."""
        signal.signal(signal.SIGINT, self._handle)
        signal.signal(signal.SIGTERM, self._handle)
        atexit.register(gc.freeze)

    def _handle(self, signum: int, frame: object) -> None:
        if self.deferring and not self.requested:
            self.requested = True
            if self.notify is not None:
                self.notify()
            return
        raise KeyboardInterrupt


@dataclass
class Point:
    """One point of a learning curve: the ``metrics.jsonl`` line, and where TensorBoard puts it.

    :param record: the line (its x key, e.g. ``iteration`` or ``game``, included).
    :param step: TensorBoard's step.
    :param axis: the curve: "" (the run's main one, ``tensorboard/``) or a name (``tensorboard/<axis>``).
    :param prefix: prepended to TensorBoard's tags.
    """

    record: dict[str, Any]
    step: int
    axis: str = ""
    prefix: str = ""

    @property
    def scalars(self) -> dict[str, float]:
        return {
            k: float(v)
            for k, v in self.record.items()
            if isinstance(v, (int, float)) and not isinstance(v, bool) and k != "axis"
        }


@dataclass
class WallClockSaves:
    """A checkpoint cadence in wall seconds, for loops whose budget is not simulated time."""

    last: float = field(default_factory=time.monotonic)

    def due(self, every_s: float) -> bool:
        """Whether ``every_s`` wall seconds have passed since the last checkpoint (which this then is)."""
        now = time.monotonic()
        if now - self.last >= every_s:
            self.last = now
            return True
        return False


class Learner(ABC):
    """A learner ``train.py`` runs (one per ``agent``): what it learns, how far it has come, what it saves.

    :param cfg: the run's (checked) config.
    :param run_dir: the run's directory.
    :param checkpoint: the checkpoint to resume from (None: a new run).
    """

    domain: ClassVar[str] = "tetris"
    agent: ClassVar[str] = ""
    unit: ClassVar[str] = "it"  # of the progress bar
    # what the learner gives the weight on H^ beyond episode ends (keys of fusion.weights.EVIDENCE)
    weight_evidence: ClassVar[frozenset[str]] = frozenset()
    # how R and H^ are put on one scale when fusion.normalise is null (fusion.fusion.SCALINGS)
    default_scaling: ClassVar[str] = "decision"

    @classmethod
    @abstractmethod
    def check(cls, cfg: DictConfig) -> None:
        """Check the learner's own config values (``agent``, ``human``, ``trainer``); the domain's group and
        the fusion weight are checked by ``config.validate_train``. Raises ``ConfigError`` with one line."""

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        self.cfg, self.run_dir = cfg, run_dir
        self.history: list[dict[str, Any]] = [] if checkpoint is None else list(checkpoint["history"])
        self.resumed = checkpoint is not None

    @property
    @abstractmethod
    def total(self) -> float:
        """The budget, in ``unit``."""

    @property
    @abstractmethod
    def position(self) -> float:
        """How far the run has come, in ``unit``."""

    @property
    def done(self) -> bool:
        return self.position >= self.total

    @property
    def description(self) -> str:
        return f"{self.agent} {self.domain}"

    @abstractmethod
    def advance(self) -> list[Point]:
        """Learn one chunk; returns the points of the curve it closed, in order."""

    @abstractmethod
    def checkpoint(self) -> dict[str, Any]:
        """What a checkpoint holds besides the config and the curve: ``state`` (to resume), ``policy`` (to
        play, ``evaluate.py``) and any task description."""

    @property
    def saves_at_start(self) -> bool:
        """Whether a new run is checkpointed before its first chunk (default: when a person teaches, so that
        a run killed in its first chunk resumes with the presses its log and journal hold)."""
        return OmegaConf.select(self.cfg, "trainer.name", default=None) == "interactive"

    def save_due(self) -> bool:
        """Whether a checkpoint is due after the chunk just learned (default: after every chunk)."""
        return True

    teaching: LiveTeaching | None = None
    """The page's server and session when a person teaches from the browser (``trainer=interactive``)."""

    @property
    def stop_requested(self) -> bool:
        """Whether the run should end after this chunk although its budget is not spent (the browser
        trainer's "Finish and save"); it then ends as a finished run, with a checkpoint."""
        return self.teaching is not None and self.teaching.finish_requested

    def interrupted(self) -> None:
        """Ctrl-C or SIGTERM asked the run to stop after the chunk in progress: a learner may end the chunk
        sooner (the browser trainer stops pacing its last steps). Called from the signal handler: set flags
        only."""
        if self.teaching is not None:
            self.teaching.session.request_stop()

    @property
    def ending(self) -> bool:
        """Whether the page asked the run to end (Finish and save, or Ctrl-C): a chunk ends at once."""
        return self.teaching is not None and self.teaching.session.ending is not None

    def end_teaching(self, budget: str, more: float) -> None:
        """Tell the page why the run ends and where it is saved (``budget`` and ``more``: the setting and
        value that continue a finished run, e.g. ``agent.frames``, 200000); call it from ``close``."""
        if self.teaching is not None:
            self.teaching.end(self.done, self.run_dir, budget, more)

    def purge_steps(self) -> dict[str, int]:
        """TensorBoard step, per axis, after which a resumed run's events are dropped (the checkpoint's)."""
        steps: dict[str, int] = {}
        for point in self.points_of(self.history):
            steps[point.axis] = max(steps.get(point.axis, 0), point.step)
        return steps

    def points_of(self, history: Sequence[dict[str, Any]]) -> list[Point]:
        """The points of saved records (TensorBoard's purge steps); learners with several axes override."""
        key = self.x_key
        return [Point(r, int(r[key])) for r in history if key in r]

    x_key: ClassVar[str] = "iteration"

    def postfix(self, point: Point) -> dict[str, str]:
        """What the progress bar shows after ``point``."""
        return {}

    def start(self, logger: Logger) -> None:  # noqa: B027  (an optional hook)
        """Called once before the first chunk (``logger``: the main TensorBoard writer; text tags)."""

    def final(self) -> dict[str, Any]:
        """The run's result: its last point (and what the learner adds)."""
        return dict(self.history[-1]) if self.history else {}

    def report(self, final: dict[str, Any]) -> list[str]:
        """Lines ``train.py`` prints at the end, above where the files are."""
        return []

    def score(self, final: dict[str, Any]) -> float | None:
        """The objective a sweeper maximises (None: none)."""
        return None

    def hparam_metrics(self, final: dict[str, Any]) -> dict[str, float]:
        """Final metrics for TensorBoard's HPARAMS view."""
        return {}

    def close(self) -> None:  # noqa: B027  (an optional hook)
        """Release what the learner holds (servers, logs); called once, also after an interruption."""


class FramesLearner(Learner):
    """A learner whose budget (``frames_total``, from ``agent.frames``) and progress (``frames``) are env
    frames of all its boards, the curve's x axis (the DQN learners, every ``domain=gym`` learner)."""

    unit = "frame"
    x_key = "frames"

    @property
    def total(self) -> float:
        return self.frames_total

    @property
    def position(self) -> float:
        return self.frames


class Callback:
    """Hooks of :func:`learn` (Stable-Baselines3's callback shape); each may be left as it is."""

    def on_start(self, learner: Learner) -> None:
        """Before the first chunk."""

    def on_point(self, learner: Learner, point: Point) -> None:
        """After a point was written."""

    def on_checkpoint(self, learner: Learner, path: Path) -> None:
        """After a checkpoint was written."""

    def on_end(self, learner: Learner, final: dict[str, Any]) -> None:
        """After the last chunk (not after an interruption)."""


@dataclass
class RunFiles:
    """A run directory's outputs: ``metrics.jsonl``, ``tensorboard/``, ``checkpoints/last.pt``."""

    run_dir: Path
    cfg: DictConfig
    loggers: dict[str, Logger] = field(default_factory=dict)

    @property
    def metrics(self) -> Path:
        return self.run_dir / "metrics.jsonl"

    @property
    def checkpoint(self) -> Path:
        return self.run_dir / "checkpoints" / LAST

    def open(self, learner: Learner) -> None:
        """Start the outputs; a resumed run's curve is rewritten from its checkpoint."""
        tmp = self.metrics.with_suffix(".jsonl.tmp")
        tmp.write_text("".join(json.dumps(r) + "\n" for r in learner.history))
        os.replace(tmp, self.metrics)
        self._purge = learner.purge_steps() if learner.resumed else {}

    def logger(self, axis: str = "") -> Logger:
        """The TensorBoard writer of ``axis`` ("" = the run's main one)."""
        if axis not in self.loggers:
            path = self.run_dir / "tensorboard" / axis if axis else self.run_dir / "tensorboard"
            purge = self._purge.get(axis)
            self.loggers[axis] = make_logger(
                self.cfg.logger.backend, path, purge_step=None if purge is None else purge + 1
            )
        return self.loggers[axis]

    def write(self, point: Point) -> None:
        """One point: to TensorBoard and as a line of ``metrics.jsonl``."""
        self.logger(point.axis).scalars(point.scalars, point.step, prefix=point.prefix)
        with self.metrics.open("a") as f:
            f.write(json.dumps(point.record) + "\n")

    def save(self, learner: Learner) -> Path:
        """Write the learner's checkpoint (atomically), with its config and curve."""
        payload = learner.checkpoint()
        path = save_checkpoint(
            self.checkpoint,
            domain=learner.domain,
            agent=learner.agent,
            config_yaml=OmegaConf.to_yaml(self.cfg, resolve=True),
            payload={**payload, "history": list(learner.history)},
        )
        for logger in self.loggers.values():
            logger.flush()
        return path

    def close(self) -> None:
        for logger in self.loggers.values():
            logger.close()


def learn(
    learner: Learner,
    files: RunFiles,
    callbacks: Sequence[Callback] = (),
    interrupt: Interrupt | None = None,
) -> dict[str, Any]:
    """Advance ``learner`` to its budget, writing every point and checkpoint; returns its result.

    An interrupt asked for during a chunk is honoured after it: a last checkpoint, then
    ``KeyboardInterrupt``. One raised inside a chunk keeps the last checkpoint and is raised again.
    """
    interrupt = interrupt if interrupt is not None else Interrupt()
    interrupt.notify = learner.interrupted
    files.open(learner)
    main = files.logger()
    if not learner.resumed:
        main.text("hyperparameters", markdown_table(flatten_config(files.cfg)))
    learner.start(main)
    for cb in callbacks:
        cb.on_start(learner)
    if not learner.resumed and learner.saves_at_start:
        files.save(learner)
    bar = tqdm(
        total=learner.total,
        initial=min(learner.position, learner.total),
        desc=learner.description,
        unit=learner.unit,
        dynamic_ncols=True,
        mininterval=1.0,
    )
    start_position, start_wall = learner.position, time.perf_counter()
    final: dict[str, Any] = {}
    try:
        while not learner.done and not interrupt.requested and not learner.stop_requested:
            interrupt.deferring = True
            points = learner.advance()
            interrupt.deferring = False
            for point in points:
                learner.history.append(point.record)
                files.write(point)
                for cb in callbacks:
                    cb.on_point(learner, point)
            if points:
                bar.set_postfix(learner.postfix(points[-1]), refresh=False)
            if learner.save_due() or learner.done or interrupt.requested or learner.stop_requested:
                path = files.save(learner)
                for cb in callbacks:
                    cb.on_checkpoint(learner, path)
            bar.update(min(learner.position, learner.total) - bar.n)
        if not interrupt.requested:
            final = learner.final()
            if final:
                final["wall_s"] = time.perf_counter() - start_wall
            if learner.position > start_position:
                # (a run too short for its first result, e.g. no keepaway episode ended, has none)
                metrics = learner.hparam_metrics(final) if final else {}
                if metrics:
                    main.hparams(flatten_config(files.cfg), metrics)
                for cb in callbacks:
                    cb.on_end(learner, final)
    finally:
        interrupt.deferring = False
        bar.close()
        learner.close()
        files.close()
    if interrupt.requested:
        raise KeyboardInterrupt
    return final
