"""Every finished keepaway episode of a batch of fields, and each field's and learner's simulated clock.

The learning curves of the keepaway learners (``experiment/learners/keepaway_sarsa.py``) and the browser
trainer's page (``interactive/keepaway_live.py``) are read from here: durations, hold shares and decisions per
keeper, per learner, over windows of simulated time or of episodes.
"""

from __future__ import annotations

import numba
import numpy as np
import torch

from hfrl_torch.common.arrays import as_numpy
from hfrl_torch.common.stats import summarize

CYCLES_PER_SECOND = 10
CYCLES_PER_MINUTE = 60 * CYCLES_PER_SECOND
CYCLES_PER_HOUR = 3600 * CYCLES_PER_SECOND


# bounds checked: the indices come from callers, and a bad one raises IndexError, not corrupts the records
_JIT = numba.njit(cache=True, nogil=True, boundscheck=True)


@_JIT
def _count_decisions(
    fields: np.ndarray, keeper: np.ndarray, action: np.ndarray, decisions: np.ndarray, holds: np.ndarray
) -> None:
    """One decision of ``keeper[i]`` on ``fields[i]``, a HoldBall where ``action[i]`` is 0."""
    for i in range(fields.shape[0]):
        decisions[fields[i], keeper[i]] += 1
        holds[fields[i]] += action[i] == 0


@_JIT
def _finish_rows(
    ended: np.ndarray,
    durations: np.ndarray,
    per_learner: int,
    finished_cycles: np.ndarray,
    clock: np.ndarray,
    episodes: np.ndarray,
    holds: np.ndarray,
    decisions: np.ndarray,
    out: np.ndarray,
) -> int:
    """The rows of the episodes that ended on ``ended`` fields, written into ``out`` in field order; the
    clocks include the ended episodes before any row reads its learner's clock. Returns the rows written."""
    for f in range(ended.shape[0]):
        if ended[f]:
            finished_cycles[f] += durations[f]
            clock[f] = finished_cycles[f]
    r = 0
    for f in range(ended.shape[0]):
        if not ended[f]:
            continue
        learner = f // per_learner
        end = 0
        for g in range(learner * per_learner, (learner + 1) * per_learner):
            end += clock[g]
        out[r, 0], out[r, 1], out[r, 2] = f, episodes[learner], end
        out[r, 3], out[r, 4] = durations[f], holds[f]
        for k in range(decisions.shape[1]):
            out[r, 5 + k] = decisions[f, k]
            decisions[f, k] = 0
        episodes[learner] += 1
        holds[f] = 0
        r += 1
    return r


class KeepawayRecords:
    """Every finished episode of every field, each field's simulated clock and each learner's (the sum
    of its ``fields_per_learner`` fields' clocks; field f belongs to learner f // fields_per_learner).

    One row per episode: field, ordinal (its number within the learner), the learner's clock at its end
    (cycles), duration (cycles), HoldBall decisions, then the decisions of each keeper.
    """

    FIELD, ORDINAL, END, DURATION, HOLDS = range(5)

    def __init__(self, fields: int, keepers: int, fields_per_learner: int = 1) -> None:
        if fields < 1 or fields_per_learner < 1 or fields % fields_per_learner:
            raise ValueError(f"{fields} fields do not split into learners of {fields_per_learner} fields")
        self.fields, self.keepers, self.fields_per_learner = fields, keepers, fields_per_learner
        self.learners = fields // fields_per_learner
        self.finished_cycles = torch.zeros(fields, dtype=torch.int64)  # clock at the current episode's start
        self.clock = torch.zeros(fields, dtype=torch.int64)
        self.episodes = torch.zeros(self.learners, dtype=torch.int64)
        self.holds = torch.zeros(fields, dtype=torch.int64)  # of the episode in progress
        self.decisions = torch.zeros(fields, keepers, dtype=torch.int64)  # of the episode in progress
        # rows in a buffer that doubles when full: a curve point reads the table, and concatenating it
        # anew for each of a long run's thousands of points copied it quadratically often
        self._buffer = torch.zeros(1024, 5 + keepers, dtype=torch.int64)
        self._count = 0

    @property
    def table(self) -> torch.Tensor:
        """All rows [E, 5 + keepers] int64, in the order the episodes ended (a view: read, do not write)."""
        return self._buffer[: self._count]

    def _reserve(self, rows: int) -> None:
        """Room for ``rows`` more rows in the buffer."""
        end = self._count + rows
        if end > self._buffer.shape[0]:
            grown = torch.zeros(max(end, 2 * self._buffer.shape[0]), self._buffer.shape[1], dtype=torch.int64)
            grown[: self._count] = self._buffer[: self._count]
            self._buffer = grown

    def _append(self, rows: torch.Tensor) -> None:
        """Add episode rows [R, 5 + keepers] after the others."""
        self._reserve(rows.shape[0])
        end = self._count + rows.shape[0]
        self._buffer[self._count : end] = rows
        self._count = end

    @property
    def learner_clock(self) -> torch.Tensor:
        """Simulated cycles of each learner [L]: its fields' clocks summed."""
        return self.clock.view(self.learners, self.fields_per_learner).sum(1)

    def learner_of(self, fields: torch.Tensor) -> torch.Tensor:
        """The learner of each field index in ``fields``."""
        return torch.div(fields, self.fields_per_learner, rounding_mode="floor")

    def decided(self, fields: torch.Tensor, keeper: torch.Tensor, action: torch.Tensor) -> None:
        """Count one decision of ``keeper`` [M] (action [M]) on each of the distinct ``fields`` [M]."""
        ints = (as_numpy(x, torch.int64) for x in (fields, keeper, action))
        _count_decisions(*ints, self.decisions.numpy(), self.holds.numpy())

    def advance(self, episode_cycles: torch.Tensor) -> None:
        """Set the clocks from the cycles [B] of the episodes in progress (or just ended)."""
        torch.add(self.finished_cycles, episode_cycles.cpu(), out=self.clock)

    def finish(self, ended: torch.Tensor, durations: torch.Tensor) -> None:
        """Record the episodes that ended on fields ``ended`` [B] with ``durations`` [B] cycles; call
        :meth:`advance` with the same step's cycles first, so that the learners' clocks include them."""
        self._reserve(self.fields)
        written = _finish_rows(
            as_numpy(ended),
            as_numpy(durations, torch.int64),
            self.fields_per_learner,
            self.finished_cycles.numpy(),
            self.clock.numpy(),
            self.episodes.numpy(),
            self.holds.numpy(),
            self.decisions.numpy(),
            self._buffer[self._count :].numpy(),
        )
        self._count += written

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Tensors that restore the records, the episodes in progress included."""
        return {
            "rows": self.table.clone(),
            "clock": self.clock.clone(),
            "episodes": self.episodes.clone(),
            "finished_cycles": self.finished_cycles.clone(),
            "holds": self.holds.clone(),
            "decisions": self.decisions.clone(),
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Continue after the saved records; records saved without their episodes in progress (before
        ``finished_cycles``) continue with fresh episodes starting at the saved clocks."""
        if state["clock"].shape != self.clock.shape or state["episodes"].shape != self.episodes.shape:
            raise ValueError(
                f"records of {state['clock'].numel()} fields / {state['episodes'].numel()} learners cannot "
                f"continue as {self.fields} fields / {self.learners} learners"
            )
        rows = state["rows"]
        self._buffer = torch.zeros(max(1024, 2 * rows.shape[0]), 5 + self.keepers, dtype=torch.int64)
        self._count = 0
        self._append(rows)
        self.clock = state["clock"].clone()
        self.episodes = state["episodes"].clone()
        if "finished_cycles" not in state:
            self.finished_cycles = state["clock"].clone()
            self.holds.zero_()
            self.decisions.zero_()
            return
        if state["decisions"].shape != self.decisions.shape or state["holds"].shape != self.holds.shape:
            raise ValueError(
                f"records of episodes in progress do not fit {self.fields} fields x {self.keepers}"
            )
        self.finished_cycles = state["finished_cycles"].clone()
        self.holds = state["holds"].clone()
        self.decisions = state["decisions"].clone()

    def summary(self, rows: torch.Tensor) -> dict[str, float]:
        """Episode duration over learners (each learner's mean in seconds over its fields' episodes,
        then mean and 95 % interval over learners), HoldBall share and decisions per episode of each
        keeper, for the episodes ``rows``."""
        table = rows.double()
        learner = self.learner_of(rows[:, self.FIELD])
        count = torch.bincount(learner, minlength=self.learners)
        total = torch.zeros(self.learners, dtype=torch.float64).index_add_(
            0, learner, table[:, self.DURATION]
        )
        seen = count > 0
        per_learner = total[seen] / count[seen] / CYCLES_PER_SECOND
        s = summarize(per_learner, floor=0.0)
        decisions = table[:, 5:]
        out = {
            "episode_s_mean": s["mean"],
            "episode_s_ci95_low": s["ci95_low"],
            "episode_s_ci95_high": s["ci95_high"],
            "episode_s_median_of_learners": s["median"],
            "learners": float(s["n"]),
            "episodes": float(table.shape[0]),
            "hold_share": float(table[:, self.HOLDS].sum() / decisions.sum().clamp(min=1)),
        }
        for k in range(self.keepers):
            out[f"decisions_per_episode_keeper{k}"] = float(decisions[:, k].mean())
        return out

    def time_window(self, start: int, stop: int) -> dict[str, float] | None:
        """Summary of the episodes that ended at learner clock [start, stop) cycles (None if none did)."""
        t = self.table
        rows = t[(t[:, self.END] >= start) & (t[:, self.END] < stop)]
        return self.summary(rows) if rows.shape[0] else None

    def episode_window(self, start: int, stop: int) -> dict[str, float]:
        """Summary of every learner's episodes number start..stop-1."""
        t = self.table
        return self.summary(t[(t[:, self.ORDINAL] >= start) & (t[:, self.ORDINAL] < stop)])
