"""compare_runs: a table over seeds, paired differences, and runs that left no metrics."""

from __future__ import annotations

import json
from pathlib import Path

from hfrl_torch.experiment.compare_runs import compare


def _run(root: Path, job: int, seed: int, curve: list[float], weight: float | None = None) -> None:
    run = root / str(job)
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(f"seed: {seed}\n")
    rows = []
    for i, lines in enumerate(curve, 1):
        row = {"iteration": i, "eval/mean_policy_lines_mean": lines}
        if weight is not None:
            row["fusion/weight_next"] = weight
        rows.append(json.dumps(row))
    (run / "metrics.jsonl").write_text("\n".join(rows) + "\n")


def test_table_paired_differences_and_crashed_runs(tmp_path):
    alone, helped = tmp_path / "alone", tmp_path / "helped"
    _run(alone, 0, 0, [10, 50, 120])
    _run(alone, 1, 1, [10, 20, 60])
    _run(helped, 0, 0, [100, 150, 200], weight=0.4)
    _run(helped, 1, 1, [20, 110, 160], weight=0.2)
    (helped / "2").mkdir()
    (helped / "2" / "config.yaml").write_text("seed: 2\n")  # crashed before its first iteration
    report = compare([alone, helped], level=100)
    assert "| alone | 2 | 90.0 [" in report  # (120 + 60) / 2
    assert "| 1 | - |" in report  # seed 1 alone never reached 100 in 3 iterations
    assert "| helped | 2 | 180.0 [" in report and "0.3 [" in report
    # paired: lines +90 on average (80, 100); iterations to 100: (1 - 3), (2 - 4) -> -2
    assert "| helped | 2 | 90.0 [" in report and "| -2.0 [" in report
    assert "helped/2: no metrics" in report
