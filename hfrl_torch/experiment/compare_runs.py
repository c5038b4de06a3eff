"""Compare conditions from their run directories: a markdown table over seeds, paired by seed.

``python -m hfrl_torch.experiment.compare_runs <sweep dir> [<sweep dir> ...] --reach 100`` reads every run
(``metrics.jsonl`` and ``config.yaml``) under each directory (a Hydra multirun folder: one condition), and
prints, per condition, the final lines per game of the mean policy, the iterations it took to reach
``--reach`` lines, and the last fusion weight, each as mean and 95 % interval over seeds; then, for every
condition after the first, the paired difference to the first (same seeds). A run with no metrics (crashed
before its first iteration) is reported and left out.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import torch
from omegaconf import OmegaConf

from hfrl_torch.common.stats import summarize

LINES = "eval/mean_policy_lines_mean"


def read_runs(sweep: Path) -> tuple[dict[int, list[dict]], list[Path]]:
    """{seed: metrics rows} of every run under ``sweep``, and the runs without metrics."""
    runs: dict[int, list[dict]] = {}
    missing: list[Path] = []
    for cfg_file in sorted(sweep.glob("**/config.yaml")):
        if cfg_file.parent.name == ".hydra":
            continue
        run = cfg_file.parent
        metrics = run / "metrics.jsonl"
        rows = (
            [json.loads(x) for x in metrics.read_text().splitlines() if x.strip()] if metrics.exists() else []
        )
        if not rows:
            missing.append(run)
            continue
        runs[int(OmegaConf.load(cfg_file).seed)] = rows
    return runs, missing


def reach(rows: list[dict], level: float) -> float:
    """The first iteration whose mean-policy lines reach ``level``; budget + 1 if none did."""
    for r in rows:
        if r[LINES] >= level:
            return float(r["iteration"])
    return float(rows[-1]["iteration"] + 1)


def _fmt(values: list[float]) -> str:
    s = summarize(torch.tensor(values, dtype=torch.float64))
    return f"{s['mean']:.1f} [{s['ci95_low']:.1f}, {s['ci95_high']:.1f}]"


def compare(sweeps: list[Path], level: float) -> str:
    """The markdown report of the conditions in ``sweeps`` (the first is the reference)."""
    table = [
        f"| condition | seeds | lines, last iteration | iterations to {level:g} lines "
        "| never reached | last weight |",
        "|---|---|---|---|---|---|",
    ]
    data = {}
    notes = []
    for sweep in sweeps:
        runs, missing = read_runs(sweep)
        notes += [f"- {m}: no metrics (crashed or not started); left out" for m in missing]
        if not runs:
            notes.append(f"- {sweep}: no runs with metrics")
            continue
        final = {s: rows[-1][LINES] for s, rows in runs.items()}
        when = {s: reach(rows, level) for s, rows in runs.items()}
        budget = {s: rows[-1]["iteration"] for s, rows in runs.items()}
        weight = [rows[-1].get("fusion/weight_next", math.nan) for rows in runs.values()]
        never = sum(when[s] > budget[s] for s in runs)
        data[sweep] = (final, when)
        w = "-" if all(math.isnan(x) for x in weight) else _fmt(weight)
        table.append(
            f"| {sweep.name} | {len(runs)} | {_fmt(list(final.values()))} | {_fmt(list(when.values()))} "
            f"| {never} | {w} |"
        )
    out = ["\n".join(table)]
    if len(data) > 1:
        ref_name = sweeps[0]
        ref = data.get(ref_name)
        paired = [
            "| condition - " + ref_name.name + " | pairs | lines, last iteration | iterations to reach |"
        ]
        paired.append("|---|---|---|---|")
        for sweep, (final, when) in list(data.items())[1:]:
            if ref is None:
                break
            seeds = sorted(set(final) & set(ref[0]))
            d_final = [final[s] - ref[0][s] for s in seeds]
            d_when = [when[s] - ref[1][s] for s in seeds]
            paired.append(f"| {sweep.name} | {len(seeds)} | {_fmt(d_final)} | {_fmt(d_when)} |")
        out.append("\n".join(paired))
    if notes:
        out.append("\n".join(notes))
    return "\n\n".join(out)


def main(argv: list[str] | None = None) -> None:
    """Command line: sweep directories, ``--reach`` level."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweeps", nargs="+", type=Path, help="one directory of runs per condition")
    parser.add_argument("--reach", type=float, default=100.0, help="lines per game to count iterations to")
    args = parser.parse_args(argv)
    for s in args.sweeps:
        if not s.is_dir():
            parser.error(f"{s} is not a directory; give one directory of runs per condition")
    print(compare(args.sweeps, args.reach))


if __name__ == "__main__":
    main()
