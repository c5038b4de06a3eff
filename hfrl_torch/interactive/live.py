"""``trainer=interactive``: a person teaches through the browser; the server, the session and the trainer."""

from __future__ import annotations

from dataclasses import dataclass

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.trainers.queue_trainer import QueueTrainer

KEY_NAMES = ("good", "bad", "pause", "presence")
# the starting speed when trainer.actions_per_s is null: Tetris placements per second (the thesis's tools:
# 5-7), keepaway decision periods per second (2 = real time at the 500 ms decisions of a taught run)
DEFAULT_SPEED = {"tetris": 5.0, "keepaway": 2.0}


@dataclass
class LiveTeaching:
    """A running browser trainer: the page's server, the shared session, and the trainer the loop drains."""

    server: TeachingServer
    session: TeachingSession
    trainer: QueueTrainer

    @classmethod
    def start(cls, server: TeachingServer, session: TeachingSession, trainer: QueueTrainer) -> LiveTeaching:
        """Start ``server``; raises ``ConfigError`` (one line) if it cannot serve where it was asked to."""
        try:
            server.start()
        except OSError as e:
            raise ConfigError(f"{e}; choose another trainer.port (0 picks a free one)") from None
        return cls(server, session, trainer)

    @property
    def url(self) -> str:
        return self.server.url

    def stop(self) -> int:
        """Stop the server (its pages closed first, so no press is acknowledged after), close the queue,
        and write every press still in it to the feedback log, so that each press a page was told was
        taken is in the log. Returns how many were written; idempotent. Call it before closing the log."""
        self.server.stop()
        queue = self.session.queue
        queue.close()
        left = queue.drain()
        if not left:
            return 0
        if self.session.log_left is not None:
            self.session.log_left(left)
        elif self.trainer.log is not None:
            self.trainer.log.extend([self.trainer.label(ev) for ev in left])
        return len(left)
