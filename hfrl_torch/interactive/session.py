"""What the training loop and the web page share: the feedback queue, speed, pause, presence and frames.

The training loop runs in the main thread, the web server in its own; this object is the only thing they
both touch, behind one lock. Feedback from the page becomes a ``FeedbackEvent`` stamped with the loop's
clock (``time.time()``) on arrival, goes into a ``FeedbackQueue`` that a ``QueueTrainer`` drains each
step, and from there into credit assignment and the feedback log like any trainer's events.

A press the page is told was taken (``ack``) is in the queue: a full queue (the loop has not drained it
for a long time) or a closed one (the run is stopping) refuses it instead, and the page is told so. What
the queue still holds when the run stops is written to the feedback log by ``LiveTeaching.stop``, through
:attr:`TeachingSession.log_left` when the trainer that drains the queue sets it.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from hfrl_torch.feedback.events import FeedbackEvent, FeedbackQueue
from hfrl_torch.interactive.messages import MAX_SPEED, MIN_SPEED, Feedback, Message, Pause, Presence, Speed

SOURCE = "human:browser"


class TeachingSession:
    """Shared state of one live teaching session.

    :param actions_per_s: the agent's starting speed while a person watches.
    :param clock: the clock of events and placements (``time.time``; tests may pass their own).
    :param sleep: how the loop waits (``time.sleep``; tests may pass their own).
    """

    def __init__(
        self,
        actions_per_s: float = 5.0,
        clock: Callable[[], float] = time.time,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not MIN_SPEED <= actions_per_s <= MAX_SPEED:
            raise ValueError(
                f"actions_per_s={actions_per_s!r} is invalid: must be in {MIN_SPEED:g}..{MAX_SPEED:g}"
            )
        self.queue = FeedbackQueue(overflow="error")  # a press acknowledged is never dropped
        self.log_left: Callable[[list[FeedbackEvent]], object] | None = None
        """Writes the presses left in the queue when the run stops to the feedback log (set by the trainer
        that drains the queue and knows how to credit them; None: ``LiveTeaching``'s ``QueueTrainer``)."""
        self.clock = clock
        self.sleep = sleep
        self._cond = threading.Condition()
        self.actions_per_s = float(actions_per_s)
        self.paused = False
        self.here = True
        self.clients = 0
        self.frame: dict[str, Any] = {"type": "status", "text": "starting"}
        self.version = 0
        self.curve: list[list[float]] = []
        self.curve_version = 0
        self.received = 0
        self.rejected = 0
        self._next_action: float | None = None

    # --- the page's side (server thread) ---

    def connect(self) -> None:
        """A page opened."""
        with self._cond:
            self.clients += 1
            self._cond.notify_all()

    def disconnect(self) -> None:
        """A page closed: with none left, the agent goes on without a teacher (and without a pause)."""
        with self._cond:
            self.clients = max(0, self.clients - 1)
            self._cond.notify_all()

    def apply(self, message: Message) -> None:
        """Act on one validated message from the page; a press the queue cannot take raises its
        ``FeedbackQueueFullError`` or ``FeedbackQueueClosedError`` (and nothing changes)."""
        with self._cond:
            if isinstance(message, Feedback):
                self.queue.put(FeedbackEvent(time=self.clock(), value=message.value, source=SOURCE))
            elif isinstance(message, Speed):
                self.actions_per_s = message.actions_per_s
            elif isinstance(message, Pause):
                self.paused = message.paused
            elif isinstance(message, Presence):
                self.here = message.here
            self.received += 1
            self._cond.notify_all()

    def reject(self) -> None:
        """Count a rejected message."""
        with self._cond:
            self.rejected += 1

    def latest(self) -> tuple[int, dict[str, Any]]:
        """The latest frame and its version number."""
        with self._cond:
            return self.version, self.frame

    def latest_curve(self) -> tuple[int, dict[str, Any]]:
        """The learning curve as a frame, and its version number (kept apart so frames never hide it)."""
        with self._cond:
            return self.curve_version, {"type": "curve", "curve": list(self.curve)}

    def settings(self) -> dict[str, Any]:
        """What the page shows of the session's state."""
        with self._cond:
            return {
                "type": "settings",
                "actions_per_s": self.actions_per_s,
                "paused": self.paused,
                "here": self.here,
                "curve": list(self.curve),
            }

    # --- the training loop's side (main thread) ---

    def teaching(self) -> bool:
        """Whether a person is watching and says they are here."""
        with self._cond:
            return self.clients > 0 and self.here

    def wait_for_page(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for a page to open; returns whether one did."""
        with self._cond:
            return self._cond.wait_for(lambda: self.clients > 0, timeout=timeout)

    def publish(self, frame: dict[str, Any]) -> None:
        """Show ``frame`` (a JSON-able dict with a ``type``) on every open page."""
        with self._cond:
            self.frame = frame
            self.version += 1

    def add_point(self, x: float, y: float) -> None:
        """Add a point (e.g. iteration, lines per game) to the page's learning curve."""
        with self._cond:
            self.curve.append([float(x), float(y)])
            self.curve_version += 1

    def wait_turn(self, actions: float = 1.0) -> float:
        """Block until the agent may take its next action (speed, pause); returns the clock's time then.

        ``actions`` is how many actions' time this turn lasts (keepaway paces each 100 ms cycle as a fifth
        of a 500 ms decision). While paused the loop waits; if the last page closes or the person leaves,
        it stops waiting.
        """
        with self._cond:
            while self.paused and self.clients > 0 and self.here:
                self._cond.wait(timeout=0.1)
            period = actions / self.actions_per_s
        now = self.clock()
        if self._next_action is not None and now < self._next_action:
            self.sleep(self._next_action - now)
            now = self.clock()
        self._next_action = now + period
        return now
