"""Aggregate finished runs into one report: ``python evaluate.py runs=<multirun dir>`` (or a list of dirs).

Every run directory below the given ones (``config.yaml`` + ``metrics.jsonl``) is read; runs are grouped by
the values that differ between them other than the seed (a Hydra sweep's swept values), and each group gets
its learning curve (mean and 95 % band over seeds), its final value (mean and 95 % interval) and, against
the reference group (the first, or ``baseline=``), the difference with a permutation-test p-value: exact
sign flips over seeds when both groups have the same seeds (paired), random relabelling otherwise, and
Cohen's d as the effect size (d_z when paired). With several conditions against the reference, Holm's
correction adjusts their p-values for the family, and the verdicts use the adjusted ones. Runs without
metrics (crashed, or killed before their first iteration) are listed and left out.

With a trainer, each point of a learner's curve also carries the human effort behind it, as the field
reports it (Knox & Stone's TAMER papers; Griffith et al. 2013): the feedback events given so far
(``feedback_events``), the trainer's minutes of watching so far (``trainer_minutes``) and the weight on H^
the learner played at (``weight``). The report then adds an effort table (events, minutes, the weight at
the start and the end), and ``effort.png`` draws performance against feedback events and the weight over
the curve's own axis.

Writes ``summary.csv``, ``per_seed.csv`` (each learner's compared value, for a paper's own statistics),
``summary.md``, ``curves.png`` (and ``effort.png``) into ``out`` (default: the first directory), and the
plots to TensorBoard as images.
"""

from __future__ import annotations

import csv
import itertools
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.stats import summarize
from hfrl_torch.fusion.weights import WEIGHT_UNUSED

# (x key, y key) of each learner's metrics.jsonl, in the order they are tried
CURVES = (
    ("iteration", "eval/mean_policy_lines_mean"),  # CE, CE + feedback
    ("game", "eval/lines_per_game_mean"),  # TAMER and the other per-game Tetris learners
    ("episode", "eval/episode_seconds_mean"),  # keepaway learners
    ("frames", "eval/greedy_lines_mean"),  # DQN on Tetris: the greedy policy's fresh games
    ("frames", "eval/greedy_episode_seconds_mean"),  # DQN keepers: the greedy policy's fresh episodes
    ("frames", "eval/greedy_return_mean"),  # domain=gym (DQN, PPO, TAMER): the greedy policy's fresh episodes
)
IGNORED = {"seed", "resume", "hydra", "logger", "threads", "device"}
EFFORT = ("feedback_events", "trainer_minutes", "weight")  # per point, with a trainer
# CE and CE + feedback log one row per iteration: (their metric, the effort key it adds up to)
CE_EFFORT = (("feedback/given", "feedback_events"), ("feedback/trainer_minutes", "trainer_minutes"))


@dataclass
class Run:
    """One finished (or crashed) run."""

    path: Path
    config: dict
    rows: list[dict] = field(default_factory=list)


@dataclass
class Group:
    """The runs that share every setting but the seed."""

    label: str
    runs: list[Run]
    x_key: str = ""
    y_key: str = ""

    @property
    def seeds(self) -> list[int]:
        return [int(r.config.get("seed", i)) for i, r in enumerate(self.runs)]

    last: int = 1
    window: tuple[float, float] | None = None

    def finals(self) -> dict[int, float]:
        """Per seed, the mean of the curve's last ``last`` points (1: the final value), or with ``window``
        (lo, hi) the mean of its points with lo < x <= hi."""
        out = {}
        for s, r in zip(self.seeds, self.runs, strict=True):
            if self.window is None:
                rows = r.rows[-self.last :]
            else:
                lo, hi = self.window
                rows = [row for row in r.rows if lo < float(row[self.x_key]) <= hi]
                if not rows:
                    raise ConfigError(
                        f"window={list(self.window)} holds no point of {r.path} (its {self.x_key} runs "
                        f"{r.rows[0][self.x_key]}..{r.rows[-1][self.x_key]})"
                    )
            out[s] = sum(float(row[self.y_key]) for row in rows) / len(rows)
        return out

    @property
    def measured(self) -> str:
        """What :meth:`finals` measures, in words."""
        if self.window is not None:
            lo, hi = self.window
            return f"{self.y_key}, mean over {self.x_key} {lo:g} < x <= {hi:g}"
        last = f" (mean of the last {self.last})" if self.last > 1 else ""
        return f"{self.y_key} at {self.x_key} {self.runs[0].rows[-1][self.x_key]}{last}"

    def reach(self, level: float) -> dict[int, float]:
        """Per seed, the first x at which the curve reaches ``level`` (the last x + 1 if it never does)."""
        out = {}
        for s, r in zip(self.seeds, self.runs, strict=True):
            hit = [row[self.x_key] for row in r.rows if row[self.y_key] >= level]
            out[s] = float(hit[0]) if hit else float(r.rows[-1][self.x_key]) + 1
        return out


def _flat(d: dict, prefix: str = "") -> dict[str, object]:
    out: dict[str, object] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def find_runs(dirs: list[Path]) -> tuple[list[Run], list[Path]]:
    """Every run below ``dirs`` and the runs without metrics."""
    runs, broken = [], []
    for d in dirs:
        if not d.is_dir():
            raise ConfigError(f"runs={str(d)!r} is not a directory; give run or multirun directories")
        for cfg_file in sorted(d.glob("**/config.yaml")):
            if cfg_file.parent.name in (".hydra", "resume-logs"):
                continue
            run_dir = cfg_file.parent
            metrics = run_dir / "metrics.jsonl"
            rows = []
            if metrics.exists():
                for line in metrics.read_text().splitlines():
                    try:
                        rows.append(json.loads(line))
                    except json.JSONDecodeError:
                        break  # a run killed mid-write: keep the lines before
            config = OmegaConf.to_container(OmegaConf.load(cfg_file), resolve=False)
            assert isinstance(config, dict)
            if not rows:
                broken.append(run_dir)
                continue
            _add_iteration_effort(rows)
            runs.extend(_learners(Run(run_dir, config, rows)))
    return runs, broken


def _add_iteration_effort(rows: list[dict]) -> None:
    """CE + feedback's rows (one per iteration) get the effort so far: events, trainer minutes, weight."""
    if not rows or "feedback/given" not in rows[-1]:
        return
    totals = dict.fromkeys(EFFORT, 0.0)
    for row in rows:
        for metric, key in CE_EFFORT:
            totals[key] += float(row.get(metric, 0.0))
            row[key] = totals[key]
        if "fusion/weight" in row:
            row["weight"] = float(row["fusion/weight"])


def _keepaway_effort(state: dict, field: int, block: int, blocks: int) -> list[dict[str, float]]:
    """Per block of a taught keepaway learner's episodes: events and trainer minutes so far, mean weight."""
    human = state.get("human")
    effort = human.get("effort") if isinstance(human, dict) else None
    if not isinstance(effort, torch.Tensor) or effort.ndim != 2 or effort.shape[1] < 5:
        return [{} for _ in range(blocks)]
    mine = effort[effort[:, 0] == field]
    mine = mine[mine[:, 1].argsort()][: blocks * block]
    if mine.shape[0] < blocks * block:
        return [{} for _ in range(blocks)]
    events, seconds = mine[:, 2].cumsum(0), mine[:, 3].cumsum(0)
    weight = mine[:, 4].view(blocks, block).mean(1)
    return [
        {
            "feedback_events": float(events[(k + 1) * block - 1]),
            "trainer_minutes": float(seconds[(k + 1) * block - 1]) / 60.0,
            "weight": float(weight[k]),
        }
        for k in range(blocks)
    ]


def _keepaway_learners(run: Run, state: dict) -> list[Run]:
    """Keepaway learners' curves from the checkpoint's episode records: each learner's mean episode
    duration (seconds) over consecutive blocks of ``agent.log_episodes`` of its first ``agent.episodes``
    episodes (all of them when the budget is in hours)."""
    records = state.get("records", {})
    rows = records.get("rows") if isinstance(records, dict) else None
    agent = run.config.get("agent", {})
    if not isinstance(rows, torch.Tensor) or rows.ndim != 2 or not isinstance(agent, dict):
        return [run]
    per_learner = int(agent.get("fields_per_learner", 1))
    learners = int(agent.get("learners", 1))
    block = max(1, int(agent.get("log_episodes", 10)))
    seed = int(run.config.get("seed", 0))
    out = []
    for i in range(learners):
        mine = rows[rows[:, 0] // per_learner == i]
        mine = mine[mine[:, 1].argsort()]
        seconds = mine[:, 3].double() / 10.0
        budget = int(agent.get("episodes", 0) or 0)
        if budget > 0:  # the run stops when its slowest learner has its budget; the others ran on
            seconds = seconds[:budget]
        full = seconds.shape[0] // block
        if full == 0:
            continue
        means = seconds[: full * block].view(full, block).mean(1).tolist()
        effort = _keepaway_effort(state, i, block, full) if per_learner == 1 else [{}] * full
        curve = [
            {"episode": (k + 1) * block, "eval/episode_seconds_mean": v, **effort[k]}
            for k, v in enumerate(means)
        ]
        out.append(Run(run.path, {**run.config, "seed": seed * 1000 + i}, curve))
    return out or [run]


def _learners(run: Run) -> list[Run]:
    """A run of L independent learners (TAMER, Q-learning, PG: one board each, lines per game in its
    checkpoint; keepaway teams, episodes in its records) as L runs with seeds ``seed * 1000 + learner``;
    any other run as itself."""
    ckpt = run.path / "checkpoints" / "last.pt"
    keepaway = run.rows[-1].get("axis") in ("hours", "episodes")
    if not ckpt.exists() or ("game" not in run.rows[-1] and not keepaway):
        return [run]
    state = torch.load(ckpt, map_location="cpu", weights_only=True).get("state", {})
    if keepaway:
        return _keepaway_learners(run, state)
    lines = state.get("lines")
    if not isinstance(lines, torch.Tensor) or lines.ndim != 2 or lines.shape[0] < 2:
        return [run]
    seed = int(run.config.get("seed", 0))
    played = int(run.rows[-1]["game"])
    effort = _games_effort(run, state, played)
    return [
        Run(
            run.path,
            {**run.config, "seed": seed * 1000 + i},
            [
                {"game": g + 1, "eval/lines_per_game_mean": float(v), **effort[i][g]}
                for g, v in enumerate(lines[i, :played].tolist())
            ],
        )
        for i in range(lines.shape[0])
    ]


def _games_effort(run: Run, state: dict, games: int) -> list[list[dict[str, float]]]:
    """Per learner and game of a taught Tetris games run: events and trainer minutes so far, its weight."""
    given, watched = state.get("given"), state.get("watched")
    learners = state["lines"].shape[0]
    if not isinstance(given, torch.Tensor) or not bool(given[..., 0].sum() > 0):
        return [[{}] * games for _ in range(learners)]
    human = run.config.get("human", {})
    per_placement = float(human.get("seconds_per_placement", 1.0)) if isinstance(human, dict) else 1.0
    events = given[:, :games, 0].double().cumsum(1)
    minutes = (
        watched[:, :games].double().cumsum(1) * per_placement / 60.0
        if isinstance(watched, torch.Tensor)
        else torch.full_like(events, float("nan"))
    )
    used = state.get("learner", {}).get("used_weight") if isinstance(state.get("learner"), dict) else None
    out = []
    for i in range(learners):
        row = []
        for g in range(games):
            point = {"feedback_events": float(events[i, g]), "trainer_minutes": float(minutes[i, g])}
            if isinstance(used, torch.Tensor):
                point["weight"] = float(used[i, g])
            row.append(point)
        out.append(row)
    return out


def group_runs(runs: list[Run]) -> list[Group]:
    """Groups of runs differing only in the ignored keys (seed, logging...), labelled by what differs."""
    flats = [_flat(r.config) for r in runs]
    keys = sorted(set().union(*flats)) if flats else []

    def distinct(k: str, members: list[dict[str, object]]) -> int:
        return len({json.dumps(f.get(k), default=str) for f in members})

    varying = []
    for k in keys:
        group, _, rest = k.partition(".")
        if group in IGNORED or distinct(k, flats) < 2:
            continue
        if rest and rest != "name" and f"{group}.name" in keys:
            # a setting of a config group counts only where it differs between runs of the same option
            by_option: dict[str, list[dict[str, object]]] = {}
            for f in flats:
                by_option.setdefault(str(f.get(f"{group}.name")), []).append(f)
            if all(distinct(k, m) < 2 for m in by_option.values()):
                continue
        varying.append(k)
    groups: dict[str, list[Run]] = {}
    for run, flat in zip(runs, flats, strict=True):
        unused = {"fusion.weight"} if flat.get("fusion.name") in WEIGHT_UNUSED else set()
        label = ", ".join(f"{k}={flat.get(k)}" for k in varying if k not in unused) or "all runs"
        groups.setdefault(label, []).append(run)
    out = []
    for label, members in groups.items():
        g = Group(label, members)
        for x, y in CURVES:
            if all(y in r.rows[-1] and x in r.rows[-1] for r in members):
                g.x_key, g.y_key = x, y
                break
        out.append(g)
    return out


def permutation_p(a: list[float], b: list[float], paired: bool, draws: int = 20_000, seed: int = 0) -> float:
    """Two-sided p-value of mean(a) - mean(b) under relabelling (sign flips when ``paired``)."""
    if paired:
        d = torch.tensor(a, dtype=torch.float64) - torch.tensor(b, dtype=torch.float64)
        observed = abs(float(d.mean()))
        n = d.numel()
        if n <= 16:
            signs = torch.tensor(list(itertools.product((1.0, -1.0), repeat=n)), dtype=torch.float64)
        else:
            g = torch.Generator().manual_seed(seed)
            signs = torch.randint(0, 2, (draws, n), generator=g).to(torch.float64) * 2 - 1
        stats = (signs * d).mean(1).abs()
        return float((stats >= observed - 1e-12).double().mean())
    x = torch.tensor(a + b, dtype=torch.float64)
    observed = abs(sum(a) / len(a) - sum(b) / len(b))
    g = torch.Generator().manual_seed(seed)
    perms = torch.argsort(torch.rand(draws, x.numel(), generator=g), dim=1)
    xa = x[perms[:, : len(a)]].mean(1)
    xb = x[perms[:, len(a) :]].mean(1)
    return float((((xa - xb).abs() >= observed - 1e-12).double().sum() + 1) / (draws + 1))


def effect_size(a: list[float], b: list[float], paired: bool) -> float:
    """Cohen's d of ``a`` against ``b``: paired, the mean difference over its standard deviation (d_z);
    unpaired, the difference of means over the pooled standard deviation. NaN where no spread is defined."""
    x, y = torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)
    if paired:
        d = x - y
        sd = float(d.std()) if d.numel() > 1 else math.nan
        return float(d.mean()) / sd if sd > 0 else math.nan
    if x.numel() < 2 or y.numel() < 2:
        return math.nan
    pooled = (((x.numel() - 1) * x.var() + (y.numel() - 1) * y.var()) / (x.numel() + y.numel() - 2)).sqrt()
    return float(x.mean() - y.mean()) / float(pooled) if float(pooled) > 0 else math.nan


def holm(p_values: list[float]) -> list[float]:
    """Holm's step-down adjustment of ``p_values`` (the family of comparisons against one reference): the
    i-th smallest p times (m - i + 1), kept monotone and at most 1."""
    m = len(p_values)
    order = sorted(range(m), key=lambda i: p_values[i])
    adjusted, running = [0.0] * m, 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


def _ci(values: list[float]) -> dict[str, float]:
    return summarize(torch.tensor(values, dtype=torch.float64))


def _curve(group: Group) -> tuple[list[float], list[float], list[float], list[float]]:
    """x, mean, band low, band high over the runs' common iterations."""
    n = min(len(r.rows) for r in group.runs)
    xs, mean, low, high = [], [], [], []
    for i in range(n):
        s = _ci([float(r.rows[i][group.y_key]) for r in group.runs])
        xs.append(float(group.runs[0].rows[i][group.x_key]))
        mean.append(s["mean"])
        low.append(s["ci95_low"])
        high.append(s["ci95_high"])
    return xs, mean, low, high


def report(
    groups: list[Group], baseline: int = 0, reach: float | None = None
) -> tuple[list[dict[str, object]], str]:
    """CSV rows and the markdown report of ``groups`` against ``groups[baseline]``; with ``reach``, also
    how long each group took to reach that level (paired differences and p-values likewise)."""
    rows: list[dict[str, object]] = []
    ref = groups[baseline]
    smallest = (1.0, 0)  # the smallest p the exact sign-flip test can give at the fewest pairs compared
    md = [
        "| condition | runs | metric | final mean | 95 % interval | difference to reference "
        "| p (permutation) | effect size (d) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    raw_p: dict[int, float] = {}  # row -> its unrounded p, for Holm's correction

    for g in groups:
        if not g.y_key:
            md.append(f"| {g.label} | {len(g.runs)} | (no known learning curve in metrics.jsonl) | | | | |")
            continue
        finals = g.finals()
        s = _ci(list(finals.values()))
        diff, p, kind, d = "", "", "", ""
        if g is not ref and ref.y_key == g.y_key:
            ref_finals = ref.finals()
            paired = sorted(finals) == sorted(ref_finals)
            a = [finals[k] for k in sorted(finals)]
            b = [ref_finals[k] for k in sorted(ref_finals)]
            diff = f"{s['mean'] - _ci(b)['mean']:+.2f}"
            kind = "paired" if paired else "unpaired"
            if min(len(a), len(b)) >= 2:  # one run per condition: no spread, so no test
                raw_p[len(rows)] = permutation_p(a, b, paired)
                p = f"{raw_p[len(rows)]:.3f}"
                size = effect_size(a, b, paired)
                d = "" if math.isnan(size) else f"{size:+.2f}"
                if paired and len(a) <= 16:
                    smallest = min(smallest, (2 / 2 ** len(a), len(a)))
        rows.append(
            {
                "condition": g.label,
                "runs": len(g.runs),
                "seeds": " ".join(map(str, sorted(finals))),
                "metric": g.y_key,
                "x": g.x_key,
                "last_x": g.runs[0].rows[-1][g.x_key],
                "mean": s["mean"],
                "ci95_low": s["ci95_low"],
                "ci95_high": s["ci95_high"],
                "difference": diff,
                "p_value": p,
                "test": kind,
                "effect_size": d,
            }
        )
        if s["n"] < 2:  # an interval of one run would have zero width: none is given
            rows[-1]["ci95_low"] = rows[-1]["ci95_high"] = ""
        ref_mark = " (reference)" if g is ref else ""
        interval = f"{s['ci95_low']:.2f} .. {s['ci95_high']:.2f}" if s["n"] >= 2 else "none (1 run)"
        test = f"{p} {kind}" if p else ("none (1 run)" if kind else "")
        md.append(
            f"| {g.label}{ref_mark} | {len(g.runs)} | {g.measured} "
            f"| {s['mean']:.2f} | {interval} | {diff} | {test} | {d} |"
        )
    tested = [rows[i] for i in raw_p]
    if len(tested) > 1:  # several conditions against one reference: Holm's correction for the family
        for r, adjusted in zip(tested, holm(list(raw_p.values())), strict=True):
            r["p_holm"] = f"{adjusted:.3f}"
        md += [
            "",
            f"{len(tested)} conditions are compared with the reference: Holm's correction for the family "
            "gives "
            + ", ".join(f"{r['condition']} p = {r['p_holm']}" for r in tested)
            + " (the verdicts below use these).",
        ]
    if smallest[1] and smallest[0] > 0.05:
        md += [
            "",
            f"With {smallest[1]} paired runs the exact sign-flip test cannot give a p below "
            f"{smallest[0]:.3f} (2 of its 2^{smallest[1]} sign patterns are always as extreme as the "
            "data): no difference can reach p < 0.05 with fewer than 6 pairs.",
        ]
    if reach is not None:
        md += ["", _reach_table(groups, ref, reach, rows)]
    if any(_has_effort(g) for g in groups):
        md += ["", _effort_table(groups, rows)]
    return rows, "\n".join(md)


def per_seed_rows(groups: list[Group]) -> list[dict[str, object]]:
    """One row per learner and condition: the value the report compares (``per_seed.csv``), for a
    paper's own statistics."""
    out: list[dict[str, object]] = []
    for g in groups:
        if g.y_key:
            finals = g.finals()
            out += [
                {"condition": g.label, "seed": k, "metric": g.y_key, "value": finals[k]}
                for k in sorted(finals)
            ]
    return out


def verdicts(rows: list[dict[str, object]], reference: str, level: float = 0.05) -> list[str]:
    """One plain sentence per condition: its final value against the reference's, and whether the
    difference is significant at ``level`` (the report's paired or unpaired permutation test)."""
    ref = next((r for r in rows if r["condition"] == reference), None)
    if ref is None:
        return []
    out = []
    for r in rows:
        if r is ref or r["p_value"] == "":
            continue
        p = float(str(r.get("p_holm") or r["p_value"]))
        diff = float(str(r["difference"]))
        named = "p (Holm)" if r.get("p_holm") else "p"
        if p < level:
            word = "higher than" if diff > 0 else "lower than"
            verdict = f"significantly {word} the reference"
        else:
            verdict = "not significantly different from the reference"
        out.append(
            f"{r['condition']}: {float(str(r['mean'])):.2f} against {float(str(ref['mean'])):.2f} for "
            f"{reference} ({diff:+.2f}, {named} = {p:.3f}, {r['runs']} seeds): {verdict} at {level:g}"
        )
    return out


def _has_effort(group: Group) -> bool:
    return bool(group.y_key) and all("feedback_events" in r.rows[-1] for r in group.runs)


def _effort_table(groups: list[Group], rows: list[dict[str, object]]) -> str:
    """The human effort of each taught group (events and trainer minutes per learner at the end, the weight
    on H^ at the first and the last point); fills the ``effort_*`` columns of ``rows``."""
    md = [
        "| condition | feedback events per learner | trainer minutes per learner | weight on H^, first point "
        "| weight on H^, last point |",
        "|---|---|---|---|---|",
    ]
    by_label = {r["condition"]: r for r in rows}
    for g in groups:
        if not _has_effort(g):
            continue
        cells, values = [], {}
        for key, at in (("feedback_events", -1), ("trainer_minutes", -1), ("weight", 0), ("weight", -1)):
            got = [float(r.rows[at][key]) for r in g.runs if key in r.rows[at]]
            s = _ci(got) if got else None
            cells.append(f"{s['mean']:.2f} ({s['ci95_low']:.2f} .. {s['ci95_high']:.2f})" if s else "")
            values[f"effort_{key}_{'first' if at == 0 else 'last'}"] = s["mean"] if s else ""
        by_label[g.label].update(values)
        md.append(f"| {g.label} | " + " | ".join(cells) + " |")
    return "\n".join(md)


def _reach_table(groups: list[Group], ref: Group, level: float, rows: list[dict[str, object]]) -> str:
    """How long each group took to reach ``level``; fills the ``reach_*`` columns of ``rows``."""
    md = [
        f"| condition | {ref.x_key or 'x'} to reach {level:g} (95 % interval) | never reached "
        "| difference to reference | p (permutation) |",
        "|---|---|---|---|---|",
    ]
    ref_when = ref.reach(level) if ref.y_key else {}
    by_label = {r["condition"]: r for r in rows}
    for g in groups:
        if not g.y_key:
            continue
        when = g.reach(level)
        last = {s: float(r.rows[-1][g.x_key]) for s, r in zip(g.seeds, g.runs, strict=True)}
        never = sum(when[s] > last[s] for s in when)
        s = _ci(list(when.values()))
        diff = p = ""
        if g is not ref and ref_when:
            paired = sorted(when) == sorted(ref_when)
            a = [when[k] for k in sorted(when)]
            b = [ref_when[k] for k in sorted(ref_when)]
            diff = f"{s['mean'] - _ci(b)['mean']:+.2f}"
            p = f"{permutation_p(a, b, paired):.3f}"
        row = by_label[g.label]
        row.update(
            {"reach_level": level, "reach_mean": s["mean"], "reach_never": never, "reach_difference": diff}
        )
        row["reach_p_value"] = p
        md.append(
            f"| {g.label} | {s['mean']:.2f} ({s['ci95_low']:.2f} .. {s['ci95_high']:.2f}) | {never} "
            f"| {diff} | {p} |"
        )
    return "\n".join(md)


def _smooth(values: list[float], window: int) -> list[float]:
    """Trailing moving average over ``window`` points (shorter at the start)."""
    out, total = [], 0.0
    for i, v in enumerate(values):
        total += v
        if i >= window:
            total -= values[i - window]
        out.append(total / min(i + 1, window))
    return out


DEPARTURE_AXES = ("iteration", "game", "episode")  # the axes trainer.leave_after (episodes) is counted on


def departures(groups: list[Group]) -> list[float]:
    """Where the trainer left, on the curves' x axis: each distinct ``trainer.leave_after`` counted in
    episodes (a CE iteration or a game is one watched episode) among the drawn groups' runs."""
    out = set()
    for g in groups:
        if g.x_key not in DEPARTURE_AXES:
            continue
        for r in g.runs:
            trainer = r.config.get("trainer") or {}
            if trainer.get("leave_after") is not None and trainer.get("leave_unit", "episodes") == "episodes":
                out.add(float(trainer["leave_after"]))
    return sorted(out)


def plot(groups: list[Group], path: Path) -> None:
    """Learning curves, mean and 95 % band over seeds, one line per group (PNG). Curves of more than 50
    points are drawn as trailing moving averages over 2 % of their length (said on the axis)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drawn = [g for g in groups if g.y_key]
    colours = plt.get_cmap("tab10" if len(drawn) <= 10 else "tab20")
    fig, ax = plt.subplots(figsize=(7, 4.2) if len(drawn) <= 6 else (8, 5.5), dpi=110)
    smoothed = False
    for i, g in enumerate(drawn):
        xs, mean, low, high = _curve(g)
        window = max(1, len(xs) // 50)
        mean, low, high = (_smooth(v, window) for v in (mean, low, high))
        smoothed = smoothed or window > 1
        colour = colours(i % colours.N)
        ax.plot(xs, mean, color=colour, label=f"{g.label} (n={len(g.runs)})")
        ax.fill_between(xs, low, high, color=colour, alpha=0.15)
    for i, x in enumerate(departures(drawn)):
        label = "the trainer leaves" if i == 0 else None
        ax.axvline(x, color="grey", linestyle="--", linewidth=1, label=label)
    ys = {g.y_key for g in groups if g.y_key}
    xk = {g.x_key for g in groups if g.x_key}
    ax.set_xlabel(", ".join(sorted(xk)) or "x")
    ax.set_ylabel((", ".join(sorted(ys)) or "y") + (" (moving average)" if smoothed else ""))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def plot_effort(groups: list[Group], path: Path) -> None:
    """Performance against feedback events given and against trainer minutes (means over seeds), and the
    weight on H^ along the curve."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drawn = [g for g in groups if _has_effort(g)]
    colours = plt.get_cmap("tab10" if len(drawn) <= 10 else "tab20")
    fig, (events_ax, minutes_ax, weight_ax) = plt.subplots(1, 3, figsize=(15, 4.2), dpi=110)
    for i, g in enumerate(drawn):
        n = min(len(r.rows) for r in g.runs)
        colour = colours(i % colours.N)
        _, mean, _, _ = _curve(g)

        def mean_of(key: str, g: Group = g, n: int = n) -> list[float]:
            return [sum(float(r.rows[k][key]) for r in g.runs) / len(g.runs) for k in range(n)]

        label = f"{g.label} (n={len(g.runs)})"
        events_ax.plot(mean_of("feedback_events"), mean[:n], color=colour, label=label)
        minutes_ax.plot(mean_of("trainer_minutes"), mean[:n], color=colour, label=label)
        if all("weight" in r.rows[k] for r in g.runs for k in range(n)):
            xs = [float(g.runs[0].rows[k][g.x_key]) for k in range(n)]
            weight_ax.plot(xs, mean_of("weight"), color=colour, label=label)
    y = ", ".join(sorted({g.y_key for g in drawn}))
    events_ax.set(xlabel="feedback events per learner, so far", ylabel=y)
    minutes_ax.set(xlabel="trainer minutes per learner, so far", ylabel=y)
    weight_ax.set(
        xlabel=", ".join(sorted({g.x_key for g in drawn})), ylabel="weight on H^ (mean over learners)"
    )
    for ax in (events_ax, minutes_ax, weight_ax):
        ax.grid(alpha=0.3)
    events_ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def baseline_index(base: str, labels: list[str]) -> int:
    """The condition ``baseline=`` names: its label ("fusion.name=linear", quoted on a command line for its
    ``=``) or, where that is unambiguous, the label's values alone (``baseline=linear``)."""
    if base in labels:
        return labels.index(base)
    values = [", ".join(part.partition("=")[2] for part in label.split(", ")) for label in labels]
    hits = [i for i, v in enumerate(values) if v == base]
    if len(hits) == 1:
        return hits[0]
    # a value with a comma is typed quoted (baseline='human_only, None'): Hydra reads it bare as a list
    typed = [repr(v) if "," in v else v for v in values]
    allowed = "; ".join(f"{v} ({label})" for v, label in zip(typed, labels, strict=True))
    raise ConfigError(f"baseline={base!r} is not one condition here; allowed: {allowed}")


def report_options(cfg: DictConfig) -> tuple[int, tuple[float, float] | None, float | None]:
    """The report's ``last``, ``window`` and ``reach`` options, checked (one-line ``ConfigError``)."""
    last = cfg.get("last") or 1
    if isinstance(last, bool) or not isinstance(last, int) or last < 1:
        raise ConfigError(f"last={last!r} is invalid: must be an integer >= 1 (points averaged at the end)")
    window = cfg.get("window")
    if window is not None:
        bounds = list(window) if OmegaConf.is_list(window) else None
        if (
            bounds is None
            or len(bounds) != 2
            or not all(isinstance(b, int | float) and not isinstance(b, bool) for b in bounds)
            or not bounds[0] < bounds[1]
        ):
            raise ConfigError(
                f"window={window!r} is invalid: must be [from, to] with from < to (the points averaged, "
                "from < x <= to)"
            )
        window = (float(bounds[0]), float(bounds[1]))
    reach = cfg.get("reach")
    if reach is not None and (isinstance(reach, bool) or not isinstance(reach, (int, float))):
        raise ConfigError(f"reach={reach!r} is invalid: must be a number (the level to time)")
    return last, window, None if reach is None else float(reach)


def aggregate(cfg: DictConfig) -> dict[str, object]:
    """``evaluate.py runs=...``: read, group, compare, write CSV, markdown, plot; print the markdown."""
    raw = cfg.runs
    dirs = [Path(str(d)) for d in (raw if OmegaConf.is_list(raw) else [raw])]
    runs, broken = find_runs(dirs)
    if not runs:
        raise ConfigError(f"runs={[str(d) for d in dirs]} holds no run with metrics.jsonl")
    groups = group_runs(runs)
    last, window, reach = report_options(cfg)
    for g in groups:
        g.last, g.window = last, window
    labels = [g.label for g in groups]
    base = cfg.get("baseline")
    baseline = 0 if base is None else baseline_index(str(base), labels)
    rows, md = report(groups, baseline, reach)
    if broken:
        md += "\n\nRuns without metrics (crashed or killed before their first iteration), left out:\n"
        md += "\n".join(f"- {b}" for b in broken)
    out = Path(str(cfg.out)) if cfg.get("out") else dirs[0]
    out.mkdir(parents=True, exist_ok=True)
    with (out / "summary.csv").open("w", newline="") as f:
        # every row's columns: an untaught reference has no effort_* columns, a taught condition does
        fields = list(dict.fromkeys(k for r in rows for k in r)) if rows else ["condition"]
        writer = csv.DictWriter(f, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows(rows)
    with (out / "per_seed.csv").open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=["condition", "seed", "metric", "value"])
        writer.writeheader()
        writer.writerows(per_seed_rows(groups))
    (out / "summary.md").write_text(md + "\n")
    plot(groups, out / "curves.png")
    plots = ["curves.png"]
    if any(_has_effort(g) for g in groups):
        plot_effort(groups, out / "effort.png")
        plots.append("effort.png")
    plots_to_tensorboard(out, plots)
    print(md)
    for line in verdicts(rows, groups[baseline].label):
        print(line)
    return {
        "runs": len(runs),
        "missing": len(broken),
        "conditions": len(groups),
        "summary_csv": str(out / "summary.csv"),
        "per_seed_csv": str(out / "per_seed.csv"),
        "summary_md": str(out / "summary.md"),
        "plot": str(out / "curves.png"),
        "plots": [str(out / name) for name in plots],
    }


def plots_to_tensorboard(out: Path, plots: list[str]) -> None:
    """The report's plots and summary.md as TensorBoard images and text under ``out/tensorboard``."""
    import numpy as np
    from PIL import Image
    from torch.utils.tensorboard import SummaryWriter

    with SummaryWriter(str(out / "tensorboard")) as w:
        for name in plots:
            image = torch.from_numpy(np.array(Image.open(out / name).convert("RGB")))
            w.add_image(f"aggregate/{Path(name).stem}", image, 0, dataformats="HWC")
        w.add_text("aggregate/summary", (out / "summary.md").read_text(), 0)
