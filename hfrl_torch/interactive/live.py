"""``trainer=interactive``: a person teaches through the browser; the server, the session and the trainer."""

from __future__ import annotations

import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase
from tqdm import tqdm

from hfrl_torch.common.checkpoint import LAST
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.interactive.journal import browser_session
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import SOURCE, TeachingSession
from hfrl_torch.trainers.base import Events
from hfrl_torch.trainers.queue_trainer import QueueTrainer

KEY_NAMES = ("good", "bad", "pause", "presence")
# the starting speed when trainer.actions_per_s is null: Tetris placements per second (1.5: a placement
# every 0.67 s, so that a press 0.3-1.0 s after a placement is filed under it; docs/browser.md), keepaway
# decision periods per second (2 = real time at the 500 ms decisions of a taught run)
DEFAULT_SPEED = {"tetris": 1.5, "keepaway": 2.0}
SUMMARY_NAME = "teaching_summary.json"  # the end-of-session summary the page showed, kept in the run
REASONS = ("finished", "finished_by_you", "stopped", "failed")


def taught_by_person(watched: str) -> str:
    """Who gives a run's feedback when a person teaches from the page, for its TensorBoard text."""
    return f"{SOURCE}: a PERSON teaching in the browser (trainer=interactive), watching {watched}"


class BrowserQueueTrainer(QueueTrainer):
    """A person's presses off the page's queue as a ``QueueTrainer``, each logged under the run's browser
    session and filed by the subclass's :meth:`label` at the clock of the last ``give``; the presses left
    when the run stops are logged too. What Tetris's and a gym task's browser trainers share.

    :param session: the page's session; its queue holds the presses (``human:browser``, wall clock).
    :param log: the feedback log every press goes to (None: not logged).
    """

    source = SOURCE

    def __init__(self, session: TeachingSession, log: FeedbackLog | None = None) -> None:
        super().__init__(session.queue, log=log)
        self.session = session
        self.press_session = "" if log is None else browser_session(log.session)
        self._now = 0.0
        session.log_left = self.log_left

    def give(
        self,
        obs: TensorDictBase,
        action: torch.Tensor,
        time: float,
        episode: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> Events:
        self._now = float(time)
        return super().give(obs, action, time, episode, active)

    def log_left(self, pressed: list[FeedbackEvent]) -> None:
        """Log the presses left in the queue when the run stops (``TeachingSession.log_left``)."""
        self._emit([[self.label(ev) for ev in pressed]])


@dataclass
class LiveTeaching:
    """A running browser trainer: the page's server, the shared session, and the trainer the loop drains."""

    server: TeachingServer
    session: TeachingSession
    trainer: Any
    """What takes the presses off the session's queue: a ``QueueTrainer`` (Tetris: ``BrowserTetrisTrainer``)
    or keepaway's ``BrowserKeeperTrainer``."""

    @classmethod
    def start(cls, server: TeachingServer, session: TeachingSession, trainer: Any) -> LiveTeaching:
        """Start ``server``; raises ``ConfigError`` (one line) if it cannot serve where it was asked to."""
        try:
            server.start()
        except OSError as e:
            raise ConfigError(f"{e}; choose another trainer.port (0 picks a free one)") from None
        return cls(server, session, trainer)

    @property
    def url(self) -> str:
        return self.server.url

    def announce(self, wait_s: float, alone: str) -> None:
        """Print the page's URL to stderr and wait up to ``wait_s`` seconds for a page to open; ``alone``
        says what the run does meanwhile when none did ("learning from the game alone")."""
        tqdm.write(f"Teach the agent in your browser: {self.url}", file=sys.stderr)
        if wait_s > 0:
            tqdm.write(f"Waiting up to {wait_s:g} s for the page to open...", file=sys.stderr)
            if not self.session.wait_for_page(wait_s):
                tqdm.write(f"No page opened: {alone} until one does.", file=sys.stderr)

    @property
    def finish_requested(self) -> bool:
        """Whether the page asked to finish and save (the run then ends after its chunk)."""
        return self.session.ending == "finishing"

    def end(self, done: bool, run_dir: Path, budget: str, more: float) -> int:
        """Stop, telling the pages why (``done``: the budget is spent; else finished from the page, failed
        with an exception on its way out, or stopped from the terminal) and where the run is saved;
        ``budget`` and ``more``: the setting and value that continue a finished run (e.g.
        ``agent.iterations``, 100). Call it from the learner's ``close``. Returns :meth:`stop`'s count."""
        error = sys.exc_info()[1]  # an exception on its way through the run loop's ``finally``
        if isinstance(error, Exception):
            reason = "failed"
        else:
            reason = "finished" if done else "finished_by_you" if self.finish_requested else "stopped"
        return self.stop(reason, saved_run(run_dir, budget if done else None, more))

    def stop(self, reason: str = "stopped", saved: dict[str, Any] | None = None) -> int:
        """Stop the server: it takes no more messages, tells every page that the run ``reason`` (one of
        :data:`REASONS`) with the session's summary and ``saved`` (where the run is, how to continue it),
        and closes them. Then close the queue and write every press still in it to the feedback log, so
        that each press a page was told was taken is in the log. Returns how many were written;
        idempotent. Call it before closing the log."""
        if reason not in REASONS:
            raise ValueError(f"LiveTeaching.stop reason={reason!r} is invalid; allowed: {', '.join(REASONS)}")
        self.session.ending = self.session.ending or "stopping"  # no more pacing, no press taken
        told: dict[str, Any] = {}

        def final() -> dict[str, Any]:  # called after the last acknowledgement: its counts are the run's
            told.update(self.session.summary(reason, saved))
            return told

        self.server.stop(final=final)
        if saved is not None and saved.get("summary_file"):  # the page's summary outlives the page
            path = Path(saved["summary_file"])
            tmp = path.with_suffix(".json.tmp")
            tmp.write_text(json.dumps(told or self.session.summary(reason, saved), indent=1) + "\n")
            os.replace(tmp, path)
        queue = self.session.queue
        queue.close()
        left = queue.drain()
        if self.session.journal is not None:
            self.session.journal.close()
        if not left:
            return 0
        if self.session.log_left is not None:
            self.session.log_left(left)
        elif isinstance(self.trainer, QueueTrainer) and self.trainer.log is not None:
            self.trainer.log.extend([self.trainer.label(ev) for ev in left])
        return len(left)


def saved_run(run_dir: Path, budget: str | None = None, more: float = 0) -> dict[str, Any]:
    """Where a run is saved and the command that continues it (with ``budget=more`` when given)."""
    checkpoint = run_dir / "checkpoints" / LAST
    extra = f" {budget}={more:g}" if budget else ""
    return {
        "run_dir": str(run_dir),
        "checkpoint": str(checkpoint) if checkpoint.exists() else None,
        "feedback_log": str(run_dir / "feedback.jsonl"),
        "resume": f"python train.py resume={run_dir}{extra}",
        "summary_file": str(run_dir / SUMMARY_NAME),
    }
