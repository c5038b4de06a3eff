"""``trainer=interactive``: a person teaches through the browser; the server, the session and the trainer."""

from __future__ import annotations

from dataclasses import dataclass

from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.validation import require_float, require_int
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.interactive.messages import MAX_SPEED, MIN_SPEED
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


def check_interactive(cfg: DictConfig) -> None:
    """Check ``trainer`` for trainer=interactive."""
    host = OmegaConf.select(cfg, "trainer.host")
    if not isinstance(host, str) or not host:
        raise ConfigError(f"trainer.host={host!r} is invalid: must be an address such as 127.0.0.1")
    require_int(cfg, "trainer.port", 0, 65535)
    if OmegaConf.select(cfg, "trainer.actions_per_s") is not None:
        require_float(cfg, "trainer.actions_per_s", MIN_SPEED, MAX_SPEED)
    require_float(cfg, "trainer.wait_for_page_s", 0.0)
    require_int(cfg, "trainer.max_message_bytes", 64, 65536)
    require_float(cfg, "trainer.max_messages_per_s", 1.0, 1000.0)
    for key, low in (("max_teachers", 1), ("max_connections", 1)):  # optional: the server's defaults
        if OmegaConf.select(cfg, f"trainer.{key}") is not None:
            require_int(cfg, f"trainer.{key}", low, 64)
    teachers, pages = _connection_limits(cfg)
    if teachers > pages:
        raise ConfigError(
            f"trainer.max_teachers={teachers} is invalid: must be at most trainer.max_connections={pages}"
        )
    token = OmegaConf.select(cfg, "trainer.token")
    if token is not None and (not isinstance(token, str) or len(token) < 8):
        raise ConfigError("trainer.token is invalid: must be null (generated) or a string of 8+ characters")
    keys = [OmegaConf.select(cfg, f"trainer.keys.{k}") for k in KEY_NAMES]
    for name, key in zip(KEY_NAMES, keys, strict=True):
        if not isinstance(key, str) or len(key) != 1:
            raise ConfigError(f"trainer.keys.{name}={key!r} is invalid: must be one character")
    if len(set(keys)) != len(keys):
        raise ConfigError(
            f"trainer.keys {dict(zip(KEY_NAMES, keys, strict=True))} must be four different keys"
        )


def _connection_limits(cfg: DictConfig) -> tuple[int, int]:
    """``(max_teachers, max_connections)``: the config's, or the server's defaults (1 and 4)."""
    teachers = OmegaConf.select(cfg, "trainer.max_teachers")
    pages = OmegaConf.select(cfg, "trainer.max_connections")
    return (1 if teachers is None else int(teachers)), (4 if pages is None else int(pages))


def start_live_teaching(cfg: DictConfig, log: FeedbackLog, view: str) -> LiveTeaching:
    """Start the page's server for ``view`` (tetris or keepaway); raises ConfigError if it cannot serve."""
    check_interactive(cfg)
    t = cfg.trainer
    speed = DEFAULT_SPEED[view] if t.actions_per_s is None else float(t.actions_per_s)
    session = TeachingSession(actions_per_s=speed)
    teachers, pages = _connection_limits(cfg)
    server = TeachingServer(
        session,
        host=t.host,
        port=int(t.port),
        token=t.token,
        keys={k: str(t["keys"][k]) for k in KEY_NAMES},
        view=view,
        max_message_bytes=int(t.max_message_bytes),
        max_messages_per_s=float(t.max_messages_per_s),
        max_teachers=teachers,
        max_connections=pages,
    )
    try:
        server.start()
    except OSError as e:
        raise ConfigError(f"{e}; choose another trainer.port (0 picks a free one)") from None
    return LiveTeaching(server, session, QueueTrainer(session.queue, log=log))
