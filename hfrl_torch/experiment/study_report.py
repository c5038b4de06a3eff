"""A study's results: ``python evaluate.py runs=<study dir>`` (the directory holding ``study.json``).

The unit is the participant. Every participant who reached the teaching step and whose run directory holds
metrics is analysed; their runs are grouped by the condition the design gave them, and the conditions are
compared BETWEEN subjects: the difference of means with an unpaired permutation test (exact over every
relabelling when there are at most :data:`EXACT_LIMIT`, else :data:`DRAWS` seeded random relabellings),
Cohen's d with the pooled sd, a 95 % interval of each mean and of each difference, and Holm's correction
over the family of comparisons (``p_holm``). A condition of one participant gets no interval and no test.

Runs of a study differ in length (people finish early): a participant's final value is the mean of their
own last ``last`` points wherever their run ended, or with ``window=[from,to]`` of their points in that
window (a participant without one is left out of that comparison and named); a curve's point at x is the
mean over the participants whose run reached x. The questionnaire's Likert items are summarised per
condition (n, mean, sd, the answers' distribution) and compared the same way (their own Holm family); text
answers go to a CSV. Simulated participants (``participant.json`` ``simulated: true``) are marked in every
table and CSV, and with any of them the title says the results are not human-subject results.
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

from hfrl_torch.common.errors import ConfigError, UserError
from hfrl_torch.common.stats import summarize
from hfrl_torch.experiment.aggregate import (
    CURVES,
    Group,
    Run,
    baseline_index,
    effect_size,
    find_runs,
    holm,
    plots_to_tensorboard,
    report_options,
)
from hfrl_torch.feedback.log import read_feedback_log
from hfrl_torch.interactive.journal import JOURNAL_NAME, PressJournalError, read_journal
from hfrl_torch.study import layout

EXACT_LIMIT = 20_000  # relabellings enumerated exactly up to this many
DRAWS = 20_000  # random relabellings beyond it (seeded)
SEED = 0
DEFAULT_DOMAIN = "tetris"  # conf/train.yaml's


@dataclass
class Participant:
    """One enrolled participant: their record, their run (learners averaged) if analysed, or why not."""

    record: dict
    path: Path
    run: Run | None = None
    learners: int = 0
    excluded: str = ""
    feedback: dict[str, object] = field(default_factory=dict)

    @property
    def code(self) -> str:
        """Their participant code."""
        return str(self.record["code"])

    @property
    def simulated(self) -> bool:
        """Whether their client said it is a script (``simulated: true``), not a person."""
        return self.record.get("simulated") is True

    @property
    def condition(self) -> str:
        """The condition label the design gave them ("" if none)."""
        return str(self.record.get("condition") or "")


@dataclass
class ParticipantGroup(Group):
    """The analysed participants of one condition (a :class:`Group` whose units are participants)."""

    members: list[Participant] = field(default_factory=list)
    left_out: list[str] = field(default_factory=list)  # codes without a point in ``window``

    @property
    def seeds(self) -> list[int]:
        """The participants' enrolment indices: the keys of :meth:`finals` (one unit per participant)."""
        return [int(p.record["index"]) for p in self.members]

    @property
    def simulated(self) -> int:
        """How many of the condition's participants are simulated."""
        return sum(p.simulated for p in self.members)

    def finals(self) -> dict[int, float]:
        """Per participant (by enrolment index), the mean of their last ``last`` points, or of their
        points in ``window``; those without a point in the window are left out (``left_out``)."""
        out, self.left_out = {}, []
        for p in self.members:
            assert p.run is not None
            rows = p.run.rows[-self.last :]
            if self.window is not None:
                lo, hi = self.window
                rows = [row for row in p.run.rows if lo < float(row[self.x_key]) <= hi]
                if not rows:
                    self.left_out.append(p.code)
                    continue
            out[int(p.record["index"])] = sum(float(row[self.y_key]) for row in rows) / len(rows)
        return out

    @property
    def measured(self) -> str:
        """What :meth:`finals` measures, in words, with the range of x where the runs ended."""
        if self.window is not None:
            lo, hi = self.window
            return f"{self.y_key}, mean over {self.x_key} {lo:g} < x <= {hi:g}"
        ends = [float(r.rows[-1][self.x_key]) for r in self.runs]
        last = f"mean of each run's last {self.last}" if self.last > 1 else "each run's last point"
        return f"{self.y_key}, {last} ({self.x_key} {min(ends):g}..{max(ends):g})"

    @property
    def named(self) -> str:
        """The label, with how many of its participants are simulated."""
        return (
            f"{self.label} [{self.simulated} of {len(self.members)} simulated]"
            if self.simulated
            else self.label
        )


def unpaired_permutation(
    a: list[float], b: list[float], draws: int = DRAWS, seed: int = SEED
) -> tuple[float, str]:
    """Two-sided p of mean(a) - mean(b) under relabelling of the pooled values, and how it was got: every
    relabelling when there are at most :data:`EXACT_LIMIT` (the share at least as extreme), else ``draws``
    seeded random ones ((hits + 1) / (draws + 1))."""
    x = torch.tensor(a + b, dtype=torch.float64)
    n, k = x.numel(), len(a)
    observed = abs(sum(a) / len(a) - sum(b) / len(b))
    total = math.comb(n, k)
    if total <= EXACT_LIMIT:
        mask = torch.zeros(total, n, dtype=torch.bool)
        for row, chosen in enumerate(itertools.combinations(range(n), k)):
            mask[row, list(chosen)] = True
        stats = ((x * mask).sum(1) / k - (x * ~mask).sum(1) / (n - k)).abs()
        hits = int((stats >= observed - 1e-12).sum())
        return hits / total, f"exact, {total} relabellings"
    g = torch.Generator().manual_seed(seed)
    perms = torch.argsort(torch.rand(draws, n, generator=g), dim=1)
    stats = (x[perms[:, :k]].mean(1) - x[perms[:, k:]].mean(1)).abs()
    hits = int((stats >= observed - 1e-12).sum())
    return (hits + 1) / (draws + 1), f"Monte Carlo, {draws} relabellings (seed {seed})"


def difference_interval(a: list[float], b: list[float]) -> tuple[float, float]:
    """95 % interval of mean(a) - mean(b): normal approximation with unpooled variances (as each mean's)."""
    x, y = torch.tensor(a, dtype=torch.float64), torch.tensor(b, dtype=torch.float64)
    diff = float(x.mean() - y.mean())
    half = 1.96 * math.sqrt(float(x.var()) / x.numel() + float(y.var()) / y.numel())
    return diff - half, diff + half


def _merged(runs: list[Run]) -> Run:
    """A participant's run of several learners (teams, boards) as one curve: the mean over learners at the
    x values all of them reached."""
    if len(runs) == 1:
        return runs[0]
    x_key = next((x for x, y in CURVES if all(x in r.rows[-1] and y in r.rows[-1] for r in runs)), "")
    if not x_key:
        return runs[0]
    by_x = [{float(row[x_key]): row for row in r.rows} for r in runs]
    common = sorted(set.intersection(*(set(m) for m in by_x)))
    rows = []
    for x in common:
        points = [m[x] for m in by_x]
        keys = set.intersection(*(set(p) for p in points))
        rows.append(
            {
                key: sum(float(p[key]) for p in points) / len(points)
                for key in keys
                if all(isinstance(p[key], int | float) and not isinstance(p[key], bool) for p in points)
            }
        )
    return Run(runs[0].path, runs[0].config, rows)


def _reached(record: dict) -> list[str]:
    """The steps a participant has entered, in the study's order."""
    steps = record.get("steps")
    entered = set(steps) if isinstance(steps, dict) else set()
    current = record.get("step")
    if current in layout.STEPS:
        entered.update(layout.STEPS[: layout.STEPS.index(current) + 1])
    return [s for s in layout.STEPS if s in entered]


def _feedback_counts(run_dir: Path) -> dict[str, object]:
    """Events in the run's feedback log (good, bad) and presses journaled by the page."""
    out: dict[str, object] = {
        "feedback_logged": 0,
        "feedback_good": 0,
        "feedback_bad": 0,
        "feedback_problem": "",
    }
    log = run_dir / "feedback.jsonl"
    if log.exists():
        contents = read_feedback_log(log)
        values = [e.value for e in contents.events]
        out.update(
            feedback_logged=len(values),
            feedback_good=sum(v > 0 for v in values),
            feedback_bad=sum(v < 0 for v in values),
            feedback_problem=str(contents.error or ""),
        )
    presses = run_dir / JOURNAL_NAME
    out["presses_journaled"] = ""
    if presses.exists():
        try:
            out["presses_journaled"] = len(read_journal(presses))
        except PressJournalError as exc:
            out["feedback_problem"] = f"{out['feedback_problem']} {exc}".strip()
    return out


def read_object(path: Path) -> dict:
    """The JSON object in ``path``; one-line ``UserError`` naming the file if it is unreadable or not one."""
    try:
        data = layout.read_json(path)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path} is corrupt or unreadable: {str(exc).splitlines()[0]}") from exc
    if not isinstance(data, dict):
        raise UserError(f"{path} is corrupt: it holds a {type(data).__name__}, not a JSON object")
    return data


def read_records(study_dir: Path) -> list[tuple[Path, dict]]:
    """Every participant's directory and record, in enrolment order, each record checked for the fields the
    report reads."""
    out = []
    for code in layout.participant_codes(study_dir):
        path = layout.participant_json(study_dir, code)
        record = read_object(path)
        for key in ("code", "step"):
            if not isinstance(record.get(key), str):
                raise UserError(f"{path} is corrupt: {key!r} is {record.get(key)!r}, must be a string")
        if record.get("condition") is not None and not isinstance(record["condition"], str):
            raise UserError(f"{path} is corrupt: 'condition' is {record['condition']!r}, must be a label")
        if not isinstance(record.get("index"), int) or isinstance(record.get("index"), bool):
            raise UserError(f"{path} is corrupt: 'index' is {record.get('index')!r}, must be an integer")
        out.append((path.parent, record))
    return sorted(out, key=lambda pair: pair[1]["index"])


def read_study_participants(study_dir: Path) -> list[Participant]:
    """Every enrolled participant; those who reached teaching and have metrics get their run."""
    out = []
    for home, record in read_records(study_dir):
        p = Participant(record, home)
        reached = _reached(record)
        rel = record.get("run_dir")
        run_dir = study_dir / rel if isinstance(rel, str) else layout.run_dir(study_dir, str(record["code"]))
        if record["step"] == layout.DECLINED:
            p.excluded = "declined"
        elif "teaching" not in reached:
            p.excluded = f"never reached teaching (at {record['step']})"
        elif not p.condition:
            p.excluded = "reached teaching without a condition"
        elif not run_dir.is_dir():
            p.excluded = "reached teaching, no run directory"
        else:
            p.feedback = _feedback_counts(run_dir)
            runs, _ = find_runs([run_dir])
            if not runs:
                p.excluded = "reached teaching, its run has no metrics"
            else:
                p.run, p.learners = _merged(runs), len(runs)
        out.append(p)
    return out


def _no_curve(p: Participant, y_key: str) -> str:
    """Why a participant's run has no point of the condition's curve (a keepaway run gets its first point
    after ``agent.log_episodes`` episodes)."""
    assert p.run is not None
    agent = p.run.config.get("agent")
    block = agent.get("log_episodes") if isinstance(agent, dict) else None
    keepaway = p.run.rows[-1].get("axis") in ("hours", "episodes")
    hint = f": a keepaway run gets one point per agent.log_episodes={block} episodes" if keepaway else ""
    return f"reached teaching, its run has no point of {y_key or 'a known learning curve'} yet{hint}"


def _groups(participants: list[Participant], order: list[str]) -> list[ParticipantGroup]:
    """One group per condition (the study's order, then any other label) with the first known curve any of
    its runs has; a participant whose run lacks that curve is left out (``excluded`` says why)."""
    labels = list(dict.fromkeys(order + [p.condition for p in participants if p.run is not None]))
    out = []
    for label in labels:
        mine = [p for p in participants if p.run is not None and p.condition == label]
        keys = next(
            (
                (x, y)
                for x, y in CURVES
                if any(y in p.run.rows[-1] and x in p.run.rows[-1] for p in mine if p.run)
            ),
            ("", ""),
        )
        for p in mine:
            assert p.run is not None
            if not all(k in p.run.rows[-1] for k in keys) or not keys[0]:
                p.excluded, p.run = _no_curve(p, keys[1]), None
        members = [p for p in mine if p.run is not None]
        g = ParticipantGroup(label, [p.run for p in members if p.run is not None], members=members)
        g.x_key, g.y_key = keys
        out.append(g)
    return out


def condition_domains(study: dict, groups: list[ParticipantGroup]) -> dict[str, str]:
    """Each condition's domain: its runs' ``domain.name``, else the last ``domain=`` of its overrides and the
    study's ``common`` (as a worker's command line has them), else train.py's default."""
    common = [str(o) for o in study.get("common") or []]
    out = {}
    for c in study.get("conditions") or []:
        if isinstance(c, dict) and "label" in c:
            args = [*map(str, c.get("overrides") or []), *common]
            named = [a.partition("=")[2] for a in args if a.startswith("domain=")]
            out[str(c["label"])] = named[-1] if named else DEFAULT_DOMAIN
    for g in groups:
        domain = g.runs[0].config.get("domain") if g.runs else None
        if isinstance(domain, dict) and domain.get("name"):
            out[g.label] = str(domain["name"])
        out.setdefault(g.label, DEFAULT_DOMAIN)
    return out


def _references(
    groups: list[ParticipantGroup], baseline: int, domains: dict[str, str]
) -> dict[str, ParticipantGroup]:
    """Each condition's reference: ``baseline`` where it has the same domain and metric, else the first
    condition that does (a study mixing Tetris and keepaway compares each domain within itself)."""
    chosen = groups[baseline]
    out = {}
    for g in groups:
        if not g.y_key:
            continue
        alike = [r for r in groups if r.y_key == g.y_key and domains[r.label] == domains[g.label]]
        out[g.label] = chosen if chosen in alike else alike[0]
    return out


def _fmt_p(p: float) -> str:
    return f"{p:.3f}"


def _tested(values: list[float], ref_values: list[float]) -> dict[str, object]:
    """Difference of means against the reference, its interval, the unpaired permutation p and Cohen's d;
    with fewer than two values on a side only the difference, and why there is no test."""
    diff = sum(values) / len(values) - sum(ref_values) / len(ref_values)
    out: dict[str, object] = {"difference": diff, "diff_ci95_low": "", "diff_ci95_high": ""}
    out.update(p_value="", test="", effect_size="")
    if min(len(values), len(ref_values)) < 2:
        out["test"] = "none (1 participant: no spread to test)"
        return out
    lo, hi = difference_interval(values, ref_values)
    p, how = unpaired_permutation(values, ref_values)
    size = effect_size(values, ref_values, paired=False)
    out.update(diff_ci95_low=lo, diff_ci95_high=hi, p_value=p, test=f"unpaired permutation, {how}")
    out["effect_size"] = "" if math.isnan(size) else size
    return out


def _holm_rows(rows: list[dict[str, object]]) -> int:
    """Fill ``p_holm`` of every tested row (Holm over them all); returns how many were tested."""
    tested = [r for r in rows if r.get("p_value", "") != ""]
    for r, adjusted in zip(tested, holm([float(str(r["p_value"])) for r in tested]), strict=True):
        r["p_holm"] = adjusted
    for r in rows:
        r.setdefault("p_holm", "")
    return len(tested)


def _cells(row: dict[str, object]) -> tuple[str, str, str, str]:
    """The difference (interval), p (how), Holm p and d cells of a compared row."""
    if row.get("difference", "") == "":
        return "", "", "", ""
    diff = f"{float(str(row['difference'])):+.2f}"
    if row["diff_ci95_low"] != "":
        diff += f" ({float(str(row['diff_ci95_low'])):+.2f} .. {float(str(row['diff_ci95_high'])):+.2f})"
    if row["p_value"] == "":
        return diff, str(row["test"]), "", ""
    how = str(row["test"]).removeprefix("unpaired permutation, ")
    d = "" if row["effect_size"] == "" else f"{float(str(row['effect_size'])):+.2f}"
    return diff, f"{_fmt_p(float(str(row['p_value'])))} ({how})", _fmt_p(float(str(row["p_holm"]))), d


def compare(
    groups: list[ParticipantGroup], refs: dict[str, ParticipantGroup]
) -> tuple[list[dict[str, object]], list[str]]:
    """The condition table: per condition its mean and interval, and against its reference the difference
    and its interval, the unpaired permutation p, its Holm adjustment over the table, and Cohen's d."""
    rows: list[dict[str, object]] = []
    shown: list[tuple[ParticipantGroup, dict[str, object]]] = []
    for g in groups:
        if not g.members or not g.y_key:
            continue
        finals = g.finals()
        kept = [p for p in g.members if int(p.record["index"]) in finals]
        row: dict[str, object] = {
            "condition": g.label,
            "participants": len(kept),
            "simulated": sum(p.simulated for p in kept),
            "codes": " ".join(p.code for p in kept),
            "left_out": " ".join(g.left_out),
            "metric": g.y_key,
            "x": g.x_key,
            "measured": g.measured,
            "reference": refs[g.label].label,
        }
        if finals:
            s = summarize(list(finals.values()))
            row.update(mean=s["mean"], sd=s["sd"])
            row.update(
                ci95_low=s["ci95_low"] if s["n"] > 1 else "", ci95_high=s["ci95_high"] if s["n"] > 1 else ""
            )
            ref_values = list(refs[g.label].finals().values())
            if g is not refs[g.label] and ref_values:
                row.update(_tested(list(finals.values()), ref_values))
        rows.append(row)
        shown.append((g, row))
    tested = _holm_rows(rows)
    md = [
        "| condition | participants | metric | final mean | 95 % interval | difference to reference "
        "(95 % interval) | p (unpaired permutation) | Holm p | effect size (d, pooled sd) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    rows_of = {id(g): row for g, row in shown}
    for g in groups:
        if not g.members:
            md.append(f"| {g.label} | 0 | (no participant analysed) | | | | | | |")
            continue
        row = rows_of[id(g)]
        count = f"{row['participants']}" + (f" of {len(g.members)}" if g.left_out else "")
        mark = " (reference)" if g is refs[g.label] else ""
        if "mean" not in row:
            md.append(f"| {g.named}{mark} | {count} | {g.measured}: no participant has a point | | | | | | |")
            continue
        interval = (
            f"{float(str(row['ci95_low'])):.2f} .. {float(str(row['ci95_high'])):.2f}"
            if row["ci95_low"] != ""
            else "none (1 participant)"
        )
        diff, p, p_holm, d = _cells(row)
        md.append(
            f"| {g.named}{mark} | {count} | {g.measured} | {float(str(row['mean'])):.2f} | {interval} "
            f"| {diff} | {p} | {p_holm} | {d} |"
        )
    if tested:
        md += [
            "",
            f"Holm's correction is over the {tested} comparison(s) of this table; the verdicts use it.",
        ]
    left = [f"{r['condition']}: {r['left_out']}" for r in rows if r.get("left_out")]
    if left:
        md += ["", "Left out of the comparison (no point in the window): " + "; ".join(left) + "."]
    return rows, md


def verdict_lines(rows: list[dict[str, object]], level: float = 0.05) -> list[str]:
    """One plain sentence per tested condition against its reference, with its Holm p."""
    means = {r["condition"]: r.get("mean") for r in rows}
    out = []
    for r in rows:
        if r.get("p_holm") in ("", None):
            continue
        p, diff = float(str(r["p_holm"])), float(str(r["difference"]))
        word = (
            ("significantly higher than" if diff > 0 else "significantly lower than")
            if p < level
            else ("not significantly different from")
        )
        out.append(
            f"{r['condition']}: {float(str(r['mean'])):.2f} against "
            f"{float(str(means[r['reference']])):.2f} for {r['reference']} "
            f"({diff:+.2f}, Holm p = {p:.3f}, {r['participants']} participants, "
            f"{r['simulated']} simulated): {word} the reference at {level:g}"
        )
    return out


def reach_table(
    groups: list[ParticipantGroup], refs: dict[str, ParticipantGroup], level: float, rows: list[dict]
) -> list[str]:
    """How long each condition's participants took to reach ``level`` (never: their last x + 1, a censored
    value at each one's own end); fills the ``reach_*`` columns."""
    md = [
        f"| condition | x to reach {level:g} (95 % interval) | never reached | difference to reference "
        "| p (unpaired permutation) |",
        "|---|---|---|---|---|",
    ]
    by_label = {r["condition"]: r for r in rows}
    for g in groups:
        if not g.y_key or g.label not in by_label:
            continue
        when = list(g.reach(level).values())
        never = sum(w > float(r.rows[-1][g.x_key]) for w, r in zip(when, g.runs, strict=True))
        s = summarize(when)
        ref = refs[g.label]
        diff = p = ""
        if g is not ref:
            other = list(ref.reach(level).values())
            diff = f"{s['mean'] - sum(other) / len(other):+.2f}"
            if min(len(when), len(other)) >= 2:
                p = _fmt_p(unpaired_permutation(when, other)[0])
        interval = f"{s['ci95_low']:.2f} .. {s['ci95_high']:.2f}" if s["n"] > 1 else "none (1 participant)"
        by_label[g.label].update(
            reach_level=level, reach_mean=s["mean"], reach_never=never, reach_difference=diff, reach_p_value=p
        )
        md.append(f"| {g.named} | {s['mean']:.2f} ({interval}) | {never} | {diff} | {p} |")
    return md


def effort_table(groups: list[ParticipantGroup], rows: list[dict]) -> list[str]:
    """Per condition, the mean per participant of the feedback logged (feedback.jsonl), and where the curve
    carries them, its events and trainer minutes at the run's end and the weight on H^ first and last."""
    md = [
        "| condition | feedback logged per participant (good / bad) | events in the curve at the end "
        "| trainer minutes | weight on H^, first point | weight on H^, last point |",
        "|---|---|---|---|---|---|",
    ]
    by_label = {r["condition"]: r for r in rows}
    for g in groups:
        if not g.members or g.label not in by_label:
            continue
        logged = [float(p.feedback.get("feedback_logged", 0) or 0) for p in g.members]
        good = [float(p.feedback.get("feedback_good", 0) or 0) for p in g.members]
        bad = [float(p.feedback.get("feedback_bad", 0) or 0) for p in g.members]
        s = summarize(logged)
        cells = [f"{s['mean']:.1f} ({sum(good) / len(good):.1f} / {sum(bad) / len(bad):.1f})"]
        values: dict[str, object] = {"effort_feedback_logged": s["mean"]}
        for key, at in (("feedback_events", -1), ("trainer_minutes", -1), ("weight", 0), ("weight", -1)):
            got = [float(r.rows[at][key]) for r in g.runs if key in r.rows[at]]
            cells.append(f"{sum(got) / len(got):.2f}" if got else "")
            values[f"effort_{key}_{'first' if at == 0 else 'last'}"] = sum(got) / len(got) if got else ""
        by_label[g.label].update(values)
        md.append(f"| {g.named} | " + " | ".join(cells) + " |")
    return md


def _aligned(
    g: ParticipantGroup, key: str, everyone: bool = False
) -> tuple[list[float], list[float], list[float], list[float], list[int]]:
    """x, mean, band low and high, and n at each x: over the participants whose run reached that x (with
    ``everyone``, only the x that every participant of the group reached)."""
    by_x: dict[float, list[float]] = {}
    for r in g.runs:
        for row in r.rows:
            if key in row:
                by_x.setdefault(float(row[g.x_key]), []).append(float(row[key]))
    xs = sorted(x for x in by_x if not everyone or len(by_x[x]) == len(g.runs))
    stats = [summarize(by_x[x]) for x in xs]
    return (
        xs,
        [s["mean"] for s in stats],
        [s["ci95_low"] for s in stats],
        [s["ci95_high"] for s in stats],
        [int(s["n"]) for s in stats],
    )


def plot_study(groups: list[ParticipantGroup], path: Path, effort: bool = False) -> None:
    """Learning curves (one panel per metric): a point at x is the mean over the participants who reached x,
    the band the 95 % interval where two or more did, the legend gives n at the start and at the end. With
    ``effort``, performance against feedback events and trainer minutes and the weight along the curve (one
    row per metric), over the x every participant of the condition reached (so the means stay comparable)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    drawn = [g for g in groups if g.y_key and g.members and (not effort or _has_effort(g))]
    metrics = list(dict.fromkeys((g.x_key, g.y_key) for g in drawn)) or [("x", "y")]
    cols = 3 if effort else 1
    fig, axes = plt.subplots(
        len(metrics), cols, figsize=(5 * cols + 2, 4.2 * len(metrics)), dpi=110, squeeze=False
    )
    colours = plt.get_cmap("tab10" if len(drawn) <= 10 else "tab20")
    for i, g in enumerate(drawn):
        row = axes[metrics.index((g.x_key, g.y_key))]
        colour = colours(i % colours.N)
        xs, mean, low, high, ns = _aligned(g, g.y_key)
        label = f"{g.named} (n={ns[0]}" + (f", {ns[-1]} at the end)" if ns[-1] != ns[0] else ")")
        if not effort:
            row[0].plot(xs, mean, color=colour, label=label)
            band = [k for k, n in enumerate(ns) if n > 1]
            row[0].fill_between(
                [xs[k] for k in band],
                [low[k] for k in band],
                [high[k] for k in band],
                color=colour,
                alpha=0.15,
            )
            continue
        xs, mean, _, _, _ = _aligned(g, g.y_key, everyone=True)
        perf = dict(zip(xs, mean, strict=True))
        for ax, key in ((row[0], "feedback_events"), (row[1], "trainer_minutes")):
            kx, kmean, _, _, _ = _aligned(g, key, everyone=True)
            ax.plot(kmean, [perf[x] for x in kx], color=colour, label=f"{g.named} (n={len(g.runs)})")
        wx, wmean, _, _, _ = _aligned(g, "weight", everyone=True)
        if wx:
            row[2].plot(wx, wmean, color=colour, label=label)
    for (x_key, y_key), row in zip(metrics, axes, strict=True):
        if effort:
            row[0].set(xlabel="feedback events per participant, so far", ylabel=y_key)
            row[1].set(xlabel="trainer minutes per participant, so far", ylabel=y_key)
            row[2].set(xlabel=x_key, ylabel="weight on H^ (mean over participants)")
        else:
            row[0].set(xlabel=x_key, ylabel=y_key)
            row[0].set_title("mean over the participants whose run reached x", fontsize=8)
        for ax in row:
            ax.grid(alpha=0.3)
        row[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _has_effort(g: ParticipantGroup) -> bool:
    return bool(g.y_key) and bool(g.runs) and all("feedback_events" in r.rows[-1] for r in g.runs)


def _items(study: dict, path: Path) -> list[dict]:
    """The questionnaire's items of ``study.json`` (id, kind likert|text, points for Likert)."""
    items = study.get("questionnaire") or []
    if not isinstance(items, list) or not all(
        isinstance(i, dict) and isinstance(i.get("id"), str) for i in items
    ):
        raise UserError(f"{path} is corrupt: 'questionnaire' must be a list of items with an 'id'")
    for item in items:
        if item.get("kind") == "likert" and not (isinstance(item.get("points"), int) and item["points"] >= 2):
            raise UserError(
                f"{path} is corrupt: Likert item {item['id']!r} has points={item.get('points')!r}"
            )
    return items


def _answers(p: Participant, items: list[dict]) -> dict[str, object]:
    """A participant's answers, each Likert answer checked against its item (one line naming the file)."""
    answers = p.record.get("answers")
    if answers is None:
        return {}
    where = p.path / layout.PARTICIPANT_JSON
    if not isinstance(answers, dict):
        raise UserError(f"{where} is corrupt: 'answers' must be an object or null")
    for item in items:
        value = answers.get(item["id"])
        bad = isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= item["points"]
        if item.get("kind") == "likert" and value is not None and bad:
            raise UserError(
                f"{where} is corrupt: answer {item['id']}={value!r} is not an integer in 1..{item['points']}"
            )
    return answers


def questionnaire(
    participants: list[Participant],
    items: list[dict],
    labels: list[str],
    reference: dict[str, str],
) -> tuple[list[dict[str, object]], list[dict[str, object]], list[str]]:
    """Per Likert item and condition: n, mean, sd, the answers' distribution and, against the condition's
    reference, the unpaired permutation test (one Holm family over every Likert comparison); the text
    answers as rows for their CSV."""
    answered = [(p, _answers(p, items)) for p in participants if p.condition]
    answered = [(p, a) for p, a in answered if a]
    labels = list(dict.fromkeys(labels + [p.condition for p, _ in answered]))
    likert_rows: list[dict[str, object]] = []
    for item in (i for i in items if i.get("kind") == "likert"):
        points = int(item["points"])
        values = {
            label: [
                (int(a[item["id"]]), p.simulated)
                for p, a in answered
                if p.condition == label and a.get(item["id"]) is not None
            ]
            for label in labels
        }
        for label in labels:
            got = [v for v, _ in values[label]]
            if not got:
                continue
            s = summarize([float(v) for v in got])
            row: dict[str, object] = {
                "item": item["id"],
                "condition": label,
                "n": len(got),
                "simulated": sum(sim for _, sim in values[label]),
                "mean": s["mean"],
                "sd": s["sd"] if len(got) > 1 else "",
                "reference": reference.get(label, ""),
                **{f"answered_{k}": got.count(k) for k in range(1, points + 1)},
            }
            ref = [float(v) for v, _ in values.get(reference.get(label, ""), [])]
            if reference.get(label) not in ("", label) and ref:
                row.update(_tested([float(v) for v in got], ref))
            likert_rows.append(row)
    tested = _holm_rows(likert_rows)
    text_rows = [
        {
            "condition": p.condition,
            "code": p.code,
            "simulated": p.simulated,
            "item": item["id"],
            "answer": a[item["id"]],
        }
        for item in items
        if item.get("kind") != "likert"
        for p, a in answered
        if a.get(item["id"]) not in (None, "")
    ]
    md = ["## Questionnaire", ""]
    if not likert_rows and not text_rows:
        return likert_rows, text_rows, [*md, "No participant has answered the questionnaire yet."]
    md += [
        "| item | condition | n | mean | sd | answers 1..points (count of each) | difference to reference "
        "(95 % interval) | p (unpaired permutation) | Holm p | effect size (d, pooled sd) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    points_of = {i["id"]: int(i["points"]) for i in items if i.get("kind") == "likert"}
    for row in likert_rows:
        dist = " ".join(str(row[f"answered_{k}"]) for k in range(1, points_of[str(row["item"])] + 1))
        sim = f" [{row['simulated']} of {row['n']} simulated]" if row["simulated"] else ""
        mark = " (reference)" if row["reference"] == row["condition"] else ""
        sd = "" if row["sd"] == "" else f"{float(str(row['sd'])):.2f}"
        diff, p, p_holm, d = _cells(row) if "difference" in row else ("", "", "", "")
        md.append(
            f"| {row['item']} | {row['condition']}{sim}{mark} | {row['n']} "
            f"| {float(str(row['mean'])):.2f} | {sd} | {dist} | {diff} | {p} | {p_holm} | {d} |"
        )
    if tested:
        md += ["", f"Holm's correction over the {tested} Likert comparison(s), a family of its own."]
    counts = {label: sum(r["condition"] == label for r in text_rows) for label in labels}
    if text_rows:
        md += [
            "",
            "Text answers are in questionnaire_text.csv: "
            + ", ".join(f"{label} {n}" for label, n in counts.items() if n)
            + ".",
        ]
    return likert_rows, text_rows, md


def _write_csv(path: Path, rows: list[dict[str, object]], first: list[str]) -> None:
    fields = list(dict.fromkeys(first + [k for r in rows for k in r]))
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields, restval="")
        writer.writeheader()
        writer.writerows(rows)


def participant_rows(
    participants: list[Participant], groups: list[ParticipantGroup]
) -> list[dict[str, object]]:
    """One row per enrolled participant: who, how far, whether analysed (and why not), the feedback counts,
    the value compared and the run's final metrics (``final:<key>``)."""
    values: dict[str, tuple[ParticipantGroup, float]] = {}
    for g in groups:
        if g.y_key and g.members:
            finals = g.finals()
            for p in g.members:
                if int(p.record["index"]) in finals:
                    values[p.code] = (g, finals[int(p.record["index"])])
    out = []
    for p in participants:
        row: dict[str, object] = {
            "code": p.code,
            "index": p.record["index"],
            "condition": p.condition,
            "simulated": p.simulated,
            "step": p.record["step"],
            "steps_reached": " ".join(_reached(p.record)),
            "ended": p.record.get("ended") or "",
            "stopped": p.record.get("stopped") is True,
            "analysed": p.run is not None,
            "excluded": p.excluded,
            "learners": p.learners or "",
            **p.feedback,
        }
        if p.run is not None:
            g, value = values.get(p.code, (None, ""))
            last = p.run.rows[-1]
            row.update(
                metric=g.y_key if g else "", x=g.x_key if g else "", value=value, points=len(p.run.rows)
            )
            row["last_x"] = last.get(g.x_key, "") if g else ""
            row.update({f"final:{k}": v for k, v in last.items() if isinstance(v, int | float)})
        out.append(row)
    return out


def _step_order(step: str) -> int:
    return layout.STEPS.index(step) if step in layout.STEPS else len(layout.STEPS)


def _header(name: str, participants: list[Participant]) -> list[str]:
    """The title and who took part: simulated and people, declined, stopped before teaching (by step)."""
    analysed = [p for p in participants if p.run is not None]
    simulated = sum(p.simulated for p in analysed)
    people = len(analysed) - simulated
    if simulated and not people:
        title = f"# Study {name}: results of SIMULATED participants, not human-subject results"
    elif simulated:
        title = (
            f"# Study {name}: results with {simulated} SIMULATED participant(s), not human-subject results"
        )
    else:
        title = f"# Study {name}: results"
    declined = sum(p.excluded == "declined" for p in participants)
    stopped = [str(p.record["step"]) for p in participants if p.excluded.startswith("never reached teaching")]
    before = {step: stopped.count(step) for step in sorted(set(stopped), key=_step_order)}
    left: dict[str, list[str]] = {}
    for p in participants:
        if p.excluded and not p.excluded.startswith(("declined", "never")):
            left.setdefault(p.excluded.removeprefix("reached teaching, "), []).append(p.code)
    other = [f"{len(codes)} ({why}: {', '.join(codes)})" for why, codes in left.items()]
    md = [
        title,
        "",
        f"Participants analysed: {len(analysed)}: {simulated} simulated (scripted clients; participant.json "
        f"simulated: true) and {people} people. Enrolled: {len(participants)}.",
        f"Not analysed: {declined} declined consent; "
        + (
            "never reached teaching: " + ", ".join(f"{n} at {step}" for step, n in before.items())
            if before
            else "none stopped before teaching"
        )
        + (f"; reached teaching but left out: {'; '.join(other)}" if other else "")
        + ".",
    ]
    if simulated:
        md.append(
            f"{simulated} of the {len(analysed)} participants are scripted clients, not people: their "
            "feedback and answers say nothing about how people teach."
        )
    return md


METHOD = (
    "Conditions are compared between subjects: one value per participant, the difference of the means with "
    "an unpaired permutation test (exact over every relabelling up to {exact}, else {draws} seeded random "
    "relabellings), Cohen's d with the pooled sd, a 95 % interval of each mean and of each difference "
    "(normal approximation), and Holm's correction over the comparisons. Runs differ in length (people "
    "finish early): {final}; the curves' point at x is the mean over the participants whose run reached x "
    "(the band where two or more did; the legend gives n at the start and the end). A participant whose "
    "run holds several learners counts once, the mean over them. Each condition is compared with the "
    "reference (the first condition, or baseline=) where both have the same domain and metric, else with "
    "the first condition that has its domain and metric: a study mixing Tetris and keepaway compares each "
    "domain within itself."
)


def aggregate_study(cfg: DictConfig, study_dir: Path) -> dict[str, object]:
    """``evaluate.py runs=<study dir>``: read the participants, compare the conditions between subjects,
    summarise the questionnaire, write the CSVs, markdown and plots; print the markdown."""
    last, window, reach = report_options(cfg)
    study = read_object(study_dir / layout.STUDY_JSON)
    items = _items(study, study_dir / layout.STUDY_JSON)
    participants = read_study_participants(study_dir)
    conditions = study.get("conditions") or []
    order = [str(c["label"]) for c in conditions if isinstance(c, dict) and "label" in c]
    groups = _groups(participants, order)
    analysed = [g for g in groups if g.members]
    if not analysed:
        raise ConfigError(
            f"runs={str(study_dir)!r} is a study with no participant whose run has a learning curve yet "
            f"({len(participants)} enrolled)"
        )
    for g in groups:
        g.last, g.window = last, window
    base = cfg.get("baseline")
    labels = [g.label for g in analysed]
    baseline = groups.index(analysed[0 if base is None else baseline_index(str(base), labels)])
    domains = condition_domains(study, groups)
    all_labels = list(
        dict.fromkeys(order + [g.label for g in groups] + [p.condition for p in participants if p.condition])
    )
    for label in all_labels:
        domains.setdefault(label, DEFAULT_DOMAIN)
    refs = _references(groups, baseline, domains)
    rows, table = compare(groups, refs)
    if window is not None:
        final = f"a participant's value is the mean of their points with {window[0]:g} < x <= {window[1]:g}"
    elif last > 1:
        final = f"a participant's value is the mean of their own last {last} points, wherever their run ended"
    else:
        final = "a participant's value is their run's last point, wherever it ended"
    name = str(study.get("name") or study_dir.name)
    md = [*_header(name, participants), "", METHOD.format(exact=EXACT_LIMIT, draws=DRAWS, final=final), ""]
    md += ["## Conditions", "", *table]
    if reach is not None:
        md += ["", *reach_table(groups, refs, reach, rows)]
    if any(_has_effort(g) for g in groups) or any(p.feedback for p in participants):
        md += ["", "## Effort", "", *effort_table(groups, rows)]
    answered = [
        label
        for label in all_labels
        if any(p.condition == label and p.record.get("answers") for p in participants)
    ]
    reference = {}
    for label in all_labels:  # the Likert items' reference: the baseline, else the first of the same domain
        alike = [r for r in answered if domains[r] == domains[label]] or [label]
        reference[label] = groups[baseline].label if groups[baseline].label in alike else alike[0]
    likert, text, q_md = questionnaire(participants, items, all_labels, reference)
    md += ["", *q_md]
    people = participant_rows(participants, groups)
    md += [
        "",
        "## Participants",
        "",
        "| code | condition | simulated | step | analysed | value compared |",
        "|---|---|---|---|---|---|",
    ]
    for r in people:
        value = r.get("value", "")
        shown = f"{value:.2f}" if isinstance(value, float) else ""
        md.append(
            f"| {r['code']} | {r['condition']} | {'yes' if r['simulated'] else 'no'} | {r['step']} "
            f"| {'yes' if r['analysed'] else 'no: ' + str(r['excluded'])} | {shown} |"
        )
    text_md = "\n".join(md)
    out = Path(str(cfg.out)) if cfg.get("out") else study_dir / layout.RESULTS
    out.mkdir(parents=True, exist_ok=True)
    _write_csv(out / "summary.csv", rows, ["condition"])
    _write_csv(out / "per_participant.csv", people, ["code", "index", "condition", "simulated"])
    _write_csv(out / "questionnaire_likert.csv", likert, ["item", "condition", "n", "simulated"])
    _write_csv(out / "questionnaire_text.csv", text, ["condition", "code", "simulated", "item", "answer"])
    (out / "summary.md").write_text(text_md + "\n")
    plot_study(groups, out / "curves.png")
    plots = ["curves.png"]
    if any(_has_effort(g) for g in groups):
        plot_study(groups, out / "effort.png", effort=True)
        plots.append("effort.png")
    plots_to_tensorboard(out, plots)
    print(text_md)
    for line in verdict_lines(rows):
        print(line)
    return {
        "study": str(study_dir),
        "participants": len(participants),
        "analysed": sum(len(g.members) for g in groups),
        "simulated": sum(g.simulated for g in groups),
        "conditions": len(analysed),
        "summary_csv": str(out / "summary.csv"),
        "per_participant_csv": str(out / "per_participant.csv"),
        "questionnaire_likert_csv": str(out / "questionnaire_likert.csv"),
        "questionnaire_text_csv": str(out / "questionnaire_text.csv"),
        "summary_md": str(out / "summary.md"),
        "plot": str(out / "curves.png"),
        "plots": [str(out / name) for name in plots],
    }


def study_dir_of(cfg: DictConfig) -> Path | None:
    """The study directory ``runs=`` names, or None for run and multirun directories; a list that mixes
    a study with other directories is refused (one study is reported alone)."""
    raw = cfg.runs
    dirs = [Path(str(d)) for d in (raw if OmegaConf.is_list(raw) else [raw])]
    studies = [d for d in dirs if layout.is_study(d)]
    if not studies:
        return None
    if len(dirs) > 1:
        raise ConfigError(
            f"runs={[str(d) for d in dirs]} mixes study directory {str(studies[0])!r} with others; give one "
            "study directory alone (runs=<study dir>)"
        )
    return studies[0]
