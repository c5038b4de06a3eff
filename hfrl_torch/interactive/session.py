"""What the training loop and the web page share: the feedback queue, speed, pause, presence and frames.

The training loop runs in the main thread, the web server in its own; this object is the only thing they
both touch, behind one lock. A press from the page becomes a ``FeedbackEvent`` stamped with the loop's
clock (``time.time()``) on arrival and filed under the frame that was on screen :data:`REACTION_S` before
it (``timeline.py``); it goes into a ``FeedbackQueue`` that the run's browser trainer drains each step, and
from there into credit assignment and the feedback log like any trainer's events.

A press the page is told was taken (``ack``, with the run's count of presses and what the press was filed
under) is in the queue, and on disk in the run's press journal (``journal.py``) when the session has one; the
page counts only those. A press is not taken (:class:`NotTaken`, and the page
is told why) while the person says they are away, while nothing they could judge is on screen (a Tetris
agent practising between games), once the run is finishing or stopping, or when the queue is full or
closed. Presses made while paused are taken, filed under the frozen frame, and logged with the source
``human:browser:paused``. What the queue still holds when the run stops is written to the feedback log by
``LiveTeaching.stop``, through :attr:`TeachingSession.log_left` when the trainer that drains the queue sets
it.

Stopping: :meth:`TeachingSession.request_stop` (Ctrl-C, from a signal handler: it only sets a flag) and
the page's ``finish`` message set :attr:`TeachingSession.ending`; from then on no press is taken, the loop
is no longer paced or paused, and the server tells every page within one poll (20 ms).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hfrl_torch.feedback.events import FeedbackEvent, FeedbackQueue
from hfrl_torch.interactive.journal import PressJournal
from hfrl_torch.interactive.messages import (
    MAX_SPEED,
    MIN_SPEED,
    Feedback,
    Finish,
    Message,
    Pause,
    Presence,
    Speed,
)
from hfrl_torch.interactive.timeline import REACTION_S, ScreenTimeline, Shown

SOURCE = "human:browser"
PAUSED_SOURCE = "human:browser:paused"  # a press made while the agent was paused (judging a frozen frame)
PRESSES_KEPT = 200  # presses the end-of-session summary lists
SLEEP_SLICE_S = 0.05  # the pacing sleeps in slices, so that a stop ends it at once
ENDINGS = ("finishing", "stopping")
# what of a message names the run's condition (its fusion and the weight on H^): a blind session
# (a study's participant must not learn their condition) leaves these out of everything the page gets
CONDITION_FIELDS = ("weight", "weight_name", "weight_sentence")


class NotTaken(RuntimeError):
    """A press the run does not take now; the text says why, for the page."""


@dataclass(frozen=True)
class Press(FeedbackEvent):
    """A press as it waits in the queue: a ``FeedbackEvent`` (wall-clock time, filed step and episode) and
    the frame it was filed under (None: the session showed none), which the trainer credits it from."""

    frame: Shown | None = None


class TeachingSession:
    """Shared state of one live teaching session.

    :param actions_per_s: the agent's starting speed while a person watches.
    :param clock: the clock of events and placements (``time.time``; tests may pass their own).
    :param sleep: how the loop waits between paced actions (default: ``time.sleep`` in slices that a stop
        ends; tests may pass their own).
    :param reaction_s: the reaction allowance: a press is filed under what was on screen this long before.
    :param reconnect_s: when the last page drops its connection, the loop holds still this long for it to
        come back before going on without the person (a network blip does not end their game).
    :param blind: leave :data:`CONDITION_FIELDS` out of every frame and of :meth:`public_info` (a study's
        participant must not learn their condition, not even from the browser's developer tools).
    """

    def __init__(
        self,
        actions_per_s: float = 5.0,
        clock: Callable[[], float] = time.time,
        sleep: Callable[[float], None] | None = None,
        reaction_s: float = REACTION_S,
        reconnect_s: float = 10.0,
        blind: bool = False,
    ) -> None:
        if not MIN_SPEED <= actions_per_s <= MAX_SPEED:
            raise ValueError(
                f"actions_per_s={actions_per_s!r} is invalid: must be in {MIN_SPEED:g}..{MAX_SPEED:g}"
            )
        if not 0 <= reaction_s <= 2:
            raise ValueError(f"reaction_s={reaction_s!r} is invalid: must be in 0..2 seconds")
        if not reconnect_s >= 0:
            raise ValueError(f"reconnect_s={reconnect_s!r} is invalid: must be at least 0 seconds")
        self.queue = FeedbackQueue(overflow="error")  # a press acknowledged is never dropped
        self.journal: PressJournal | None = None
        """Where each press is written, fsync'd, before the page is told it was taken (None: nowhere, the
        press is saved once the loop logs it); set with the run's feedback log (``make_live_teaching``)."""
        self.log_left: Callable[[list[FeedbackEvent]], object] | None = None
        """Writes the presses left in the queue when the run stops to the feedback log (set by the trainer
        that drains the queue and knows how to credit them; None: ``LiveTeaching``'s ``QueueTrainer``)."""
        self.clock = clock
        self.sleep = self._sleep if sleep is None else sleep
        self.reaction_s = float(reaction_s)
        self.reconnect_s = float(reconnect_s)
        self.blind = bool(blind)
        self._dropped_at: float | None = None
        self.timeline = ScreenTimeline()
        self.info: dict[str, Any] = {}
        """What the page shows about the run and never changes during it (the weight's explanation, the
        units of the curve, the budget), set by whoever builds the session."""
        self._cond = threading.Condition()
        self.actions_per_s = float(actions_per_s)
        self.paused = False
        self.here = True
        self.live = True
        """Whether a game the person can judge is on screen (False while a Tetris agent practises)."""
        self.ending: str | None = None
        """``finishing`` (the page asked to finish and save) or ``stopping`` (Ctrl-C or SIGTERM); None while
        the run goes on. Set without the lock (a signal handler sets it): a plain attribute."""
        self.clients = 0
        self.frame: dict[str, Any] = {"type": "status", "text": "starting"}
        self.version = 0
        self.curve: list[list[float]] = []
        self.curve_version = 0
        self.progress: dict[str, Any] = {}
        self.settings_version = 0
        self.received = 0
        self.rejected = 0
        self.taken = 0
        self.taken_good = 0
        self.taken_paused = 0
        self.not_taken = 0
        self.presses: deque[dict[str, Any]] = deque(maxlen=PRESSES_KEPT)
        self._next_action: float | None = None

    def conceal(self, message: dict[str, Any]) -> dict[str, Any]:
        """``message`` as the page may see it: without :data:`CONDITION_FIELDS` when the session is blind."""
        if not self.blind:
            return message
        return {k: v for k, v in message.items() if k not in CONDITION_FIELDS}

    def public_info(self) -> dict[str, Any]:
        """:attr:`info` as the page may see it (:meth:`conceal`)."""
        return self.conceal(self.info)

    # --- the page's side (server thread) ---

    def connect(self) -> None:
        """A page opened."""
        with self._cond:
            self.clients += 1
            self._dropped_at = None
            self._cond.notify_all()

    def disconnect(self) -> None:
        """A page closed: with none left, the agent goes on without a teacher (and without a pause), once
        ``reconnect_s`` has passed without a page coming back."""
        with self._cond:
            self.clients = max(0, self.clients - 1)
            if self.clients == 0:
                self._dropped_at = self.clock()
            self._cond.notify_all()

    def apply(
        self, message: Message, on_screen: int | None = None, at: float | None = None
    ) -> dict[str, Any]:
        """Act on one validated message from the page; returns what its acknowledgement tells the page (for
        a press: its id, the run's count of presses taken and what it was filed under). A press that is not
        taken raises :class:`NotTaken`, ``FeedbackQueueFullError`` or ``FeedbackQueueClosedError`` (and
        nothing changes).

        :param on_screen: the version of the frame the pressing page had on screen ``reaction_s`` before
            ``at`` (the server knows what it sent to each page; -1: nothing yet); None: the frame the
            session published then.
        :param at: when the press arrived (the session's clock; None: now).
        """
        with self._cond:
            reply: dict[str, Any] = {}
            if isinstance(message, Feedback):
                reply = self._take(message, self.clock() if at is None else at, on_screen)
            elif isinstance(message, Speed):
                self.actions_per_s = message.actions_per_s
            elif isinstance(message, Pause):
                self.paused = message.paused
            elif isinstance(message, Presence):
                self.here = message.here
            elif isinstance(message, Finish) and self.ending is None:
                self.ending = "finishing"
            self.received += 1
            if not isinstance(message, Feedback):
                self.settings_version += 1
            self._cond.notify_all()
            return reply

    def _why_not(self) -> str | None:
        if self.ending == "finishing":
            return "the run is finishing and saving; this press was not saved"
        if self.ending is not None:
            return "the run is stopping; this press was not saved"
        if not self.here:
            return "you said you are away; press I'm here to teach again"
        if not self.live and not len(self.timeline):
            return "the run is starting: nothing is on screen to judge yet"
        if not self.live:
            return "the agent is practising on its own; presses count again when it plays on screen"
        return None

    def _take(self, message: Feedback, now: float, on_screen: int | None) -> dict[str, Any]:
        why = self._why_not()
        if why is None:
            if on_screen is None:
                seen = self.timeline.at(now - self.reaction_s)
            elif on_screen < 0:
                seen = None
                if len(self.timeline):
                    why = f"the page had only just connected {self.reaction_s:g} s before this press"
            else:
                seen = self.timeline.version(on_screen)
                if seen is None and len(self.timeline):
                    why = f"nothing to judge was on screen {self.reaction_s:g} s before this press"
            if seen is not None and seen.step < 0:
                why = f"no move had been made yet {self.reaction_s:g} s before this press: nothing to judge"
        if why is not None:
            self.not_taken += 1
            raise NotTaken(why)
        episode, step, label = (-1, -1, "") if seen is None else (seen.episode, seen.step, seen.label)
        source = PAUSED_SOURCE if self.paused else SOURCE
        press = Press(time=now, value=message.value, source=source, step=step, episode=episode, frame=seen)
        self.queue.check_room()  # a press that cannot be queued is refused before it is journaled
        if self.journal is not None:
            try:
                self.journal.write(now, message.value, source, seen)
            except OSError as e:
                self.not_taken += 1
                raise NotTaken(
                    f"this press could not be saved on the run's disk ({e.strerror or e})"
                ) from None
        self.queue.put(press)
        self.taken += 1
        self.taken_good += message.value > 0
        self.taken_paused += self.paused
        filed = {"value": message.value, "filed": label, "episode": episode, "step": step}
        self.presses.append({**filed, "paused": self.paused})
        return {"id": message.id, "given": self.taken, "paused": self.paused, **filed}

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
            return self.curve_version, {"type": "curve", "curve": [list(p) for p in self.curve]}

    def settings_key(self) -> tuple[int, str | None]:
        """Changes whenever :meth:`settings` does (the server polls it)."""
        return self.settings_version, self.ending

    def settings(self) -> dict[str, Any]:
        """What the page shows of the session's state."""
        with self._cond:
            return {
                "type": "settings",
                "actions_per_s": self.actions_per_s,
                "paused": self.paused,
                "here": self.here,
                "live": self.live,
                "ending": self.ending,
                "given": self.taken,
                "progress": dict(self.progress),
                "curve": [list(p) for p in self.curve],
            }

    def summary(self, reason: str, saved: dict[str, Any] | None = None) -> dict[str, Any]:
        """The end-of-session message: why the run ended (``finished``, ``finished_by_you``, ``stopped``),
        the presses taken, the curve (each point marked taught or not) and ``saved`` (where the run is and
        how to continue it)."""
        with self._cond:
            return {
                "type": "end",
                "reason": reason,
                "given": self.taken,
                "good": self.taken_good,
                "bad": self.taken - self.taken_good,
                "paused": self.taken_paused,
                "not_taken": self.not_taken,
                "presses": list(self.presses),
                "curve": [list(p) for p in self.curve],
                **(saved or {}),
            }

    # --- the training loop's side (main thread; request_stop from a signal handler too) ---

    def page_open(self) -> bool:
        """Whether a page is open. Within ``reconnect_s`` of the last page dropping out, this waits for it
        to come back (the loop holds still meanwhile) and says whether it did."""
        if self.clients > 0:
            return True
        if self._dropped_at is None:
            return False
        with self._cond:
            while self.clients == 0 and self._dropped_at is not None and self.ending is None:
                left = self._dropped_at + self.reconnect_s - self.clock()
                if left <= 0:
                    self._dropped_at = None
                    break
                self._cond.wait(timeout=min(left, 0.1))
            return self.clients > 0

    def teaching(self) -> bool:
        """Whether a person is watching and says they are here (see :meth:`page_open` for a dropped page)."""
        return self.page_open() and self.here

    def wait_for_page(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for a page to open; returns whether one did."""
        with self._cond:
            return self._cond.wait_for(lambda: self.clients > 0, timeout=timeout)

    def request_stop(self) -> None:
        """Ctrl-C or SIGTERM: stop taking presses and pacing; the pages are told. Safe in a signal handler
        (it sets one attribute)."""
        self.ending = "stopping"

    def publish(self, frame: dict[str, Any]) -> None:
        """Show ``frame`` (a JSON-able dict with a ``type``) on every open page (:meth:`conceal`'d)."""
        frame = self.conceal(frame)
        with self._cond:
            self.frame = frame
            self.version += 1

    def shown(self, sim: float, episode: int, step: int, label: str = "") -> float:
        """Record that the frame just published shows the moment ``sim`` of the game's clock (``step``: the
        placement or decision a press on it judges, -1: none); returns the wall time recorded."""
        with self._cond:
            wall = self.clock()
            self.timeline.shown(wall, sim, episode, step, label, self.version)
            return wall

    def filed(self, event: FeedbackEvent) -> tuple[Shown | None, Shown | None]:
        """The frame ``event`` is filed under (a :class:`Press`'s own; for another event, the one published
        ``reaction_s`` before its time) and the next frame of another step after it (None: none)."""
        with self._cond:
            seen = event.frame if isinstance(event, Press) else self.timeline.at(event.time - self.reaction_s)
            return seen, None if seen is None else self.timeline.after(seen)

    def set_live(self, live: bool) -> None:
        """Say whether a game the person can judge is on screen."""
        with self._cond:
            self.live = bool(live)
            self.settings_version += 1

    def set_progress(self, **progress: Any) -> None:
        """What is left of the run, for the page (e.g. ``round``, ``rounds``, ``left_s``)."""
        with self._cond:
            self.progress = progress
            self.settings_version += 1

    def add_point(self, x: float, y: float, taught: float = 0.0) -> None:
        """Add a point (e.g. practice round, lines per game) to the page's learning curve; ``taught``: the
        share of it the person taught (0..1)."""
        with self._cond:
            self.curve.append([float(x), float(y), float(taught)])
            self.curve_version += 1

    def wait_turn(self, actions: float = 1.0) -> float:
        """Block until the agent may take its next action (speed, pause); returns the clock's time then.

        ``actions`` is how many actions' time this turn lasts (keepaway paces each 100 ms cycle as a fifth
        of a 500 ms decision). While paused the loop waits; if the last page closes, the person leaves or
        the run is ending, it stops waiting (an ending run is not paced at all).
        """
        with self._cond:
            while self.paused and self.clients > 0 and self.here and self.ending is None:
                self._cond.wait(timeout=0.1)
            period = actions / self.actions_per_s
        now = self.clock()
        if self.ending is not None:
            self._next_action = None
            return now
        if self._next_action is not None and now < self._next_action:
            self.sleep(self._next_action - now)
            now = self.clock()
        self._next_action = now + period
        return now

    def _sleep(self, seconds: float) -> None:
        """``time.sleep(seconds)``, cut short once the run is ending."""
        end = time.monotonic() + seconds
        while self.ending is None:
            left = end - time.monotonic()
            if left <= 0:
                return
            time.sleep(min(left, SLEEP_SLICE_S))
