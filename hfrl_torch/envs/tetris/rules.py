"""The rule set of a Tetris game: board size and the options that change scores."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class TetrisRules:
    """Simplified rules by default; every result names its rule set via :meth:`describe`.

    :param width: columns (4..30).
    :param height: rows (4..1000).
    :param bag: 7-bag piece generator instead of i.i.d. uniform pieces.
    :param spawn_topout: the game also ends when the next piece cannot spawn at the top centre.
    :param preview: the next piece is observable.
    """

    width: int = 10
    height: int = 20
    bag: bool = False
    spawn_topout: bool = False
    preview: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.width, int) or not 4 <= self.width <= 30:
            raise ValueError(f"board width={self.width!r} is invalid: must be an integer in 4..30")
        if not isinstance(self.height, int) or not 4 <= self.height <= 1000:
            raise ValueError(f"board height={self.height!r} is invalid: must be an integer in 4..1000")

    def describe(self) -> str:
        """Short rule-set name, e.g. ``simplified`` or ``simplified+bag+topout``."""
        extra = [
            n for n, on in (("bag", self.bag), ("topout", self.spawn_topout), ("preview", self.preview)) if on
        ]
        return "+".join(["simplified", *extra])

    def as_dict(self) -> dict[str, object]:
        """The rules as plain values (for checkpoints)."""
        return asdict(self)
