"""Feature sets over Tetris boards: their ids, sizes and names.

The computation itself lives in each engine (``engine_numba`` and ``engine_torch``);
this module is the single description both follow and that configs refer to.
"""

from __future__ import annotations

from dataclasses import dataclass

BT = 0
KNOX = 1
DELLACHERIE = 2
DT = 3

_IDS = {"bt": BT, "knox": KNOX, "dellacherie": DELLACHERIE, "dt": DT}
FEATURE_SETS: tuple[str, ...] = tuple(_IDS)  # the feature sets by name


@dataclass(frozen=True)
class FeatureSet:
    """A named feature set for a board ``width`` columns wide."""

    name: str
    fid: int
    width: int

    @property
    def size(self) -> int:
        return feature_size(self.fid, self.width)

    @property
    def names(self) -> list[str]:
        return feature_names(self.fid, self.width)


def feature_id(name: str) -> int:
    """Numeric id of a feature-set name; raises ValueError naming the allowed ones."""
    if name not in _IDS:
        raise ValueError(f"unknown feature set {name!r}; allowed: {', '.join(sorted(_IDS))}")
    return _IDS[name]


def feature_size(fid: int, width: int) -> int:
    """Number of features of set ``fid`` on a board ``width`` wide (BT: 21, Knox: 46 on 10 wide)."""
    if fid == BT:
        return 2 * width + 1
    if fid == KNOX:
        return 2 * (2 * width + 3)
    if fid == DELLACHERIE:
        return 6
    if fid == DT:
        return 9
    raise ValueError(f"unknown feature id {fid}; allowed: 0 (bt), 1 (knox), 2 (dellacherie), 3 (dt)")


def feature_names(fid: int, width: int) -> list[str]:
    """Human-readable names in engine order, for TensorBoard and checkpoints."""
    bt = (
        [f"height_{c}" for c in range(width)]
        + [f"abs_diff_{c}_{c + 1}" for c in range(width - 1)]
        + ["max_height", "holes"]
    )
    if fid == BT:
        return bt
    if fid == KNOX:
        base = [*bt, "max_well_depth", "sum_well_depths"]
        return base + [f"{n}_sq" for n in base]
    dell = ["landing_height", "eroded_cells", "row_transitions", "col_transitions", "holes", "wells"]
    if fid == DELLACHERIE:
        return dell
    if fid == DT:
        return [*dell, "hole_depth", "rows_with_holes", "pattern_diversity"]
    raise ValueError(f"unknown feature id {fid}")


def feature_set(name: str, width: int) -> FeatureSet:
    """The feature set called ``name`` ("bt", "knox", "dellacherie", "dt") for ``width`` columns."""
    return FeatureSet(name=name, fid=feature_id(name), width=width)


# Dellacherie's hand-tuned weights over the Dellacherie 6 (Fahey's report of Dellacherie's player).
DELLACHERIE_WEIGHTS: tuple[float, ...] = (-1.0, 1.0, -1.0, -1.0, -4.0, -1.0)
