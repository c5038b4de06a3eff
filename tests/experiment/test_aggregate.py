"""evaluate.py runs=...: grouping by what differs, intervals, permutation tests, files, crashed runs."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from script_runner import run_script

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment.aggregate import (
    aggregate,
    baseline_index,
    departures,
    effect_size,
    find_runs,
    group_runs,
    holm,
    permutation_p,
    report,
    verdicts,
)

ROOT = Path(__file__).resolve().parents[2]


def _run(root: Path, name: str, config: str, curve: list[float]) -> None:
    run = root / name
    run.mkdir(parents=True)
    (run / "config.yaml").write_text(config)
    rows = [json.dumps({"iteration": i, "eval/mean_policy_lines_mean": y}) for i, y in enumerate(curve, 1)]
    (run / "metrics.jsonl").write_text("\n".join(rows) + "\n")


def _sweep(root: Path) -> None:
    for seed, (a, b) in enumerate([(10, 30), (20, 50), (30, 40), (40, 80)]):
        base = f"seed: {seed}\nthreads: 1\nagent:\n  name: cem\n  population: 100\n"
        _run(root, f"{seed}", base + "fusion:\n  name: none\n", [1, a])
        _run(root, f"{seed + 10}", base + "fusion:\n  name: linear\n  weight: trust\n", [2, b])
    crashed = root / "99"
    crashed.mkdir()
    (crashed / "config.yaml").write_text("seed: 99\nfusion:\n  name: linear\n")


def test_groups_by_what_differs_and_compares_paired(tmp_path):
    _sweep(tmp_path)
    runs, broken = find_runs([tmp_path])
    assert len(runs) == 8 and broken == [tmp_path / "99"]
    groups = group_runs(runs)
    assert [g.label for g in groups] == ["fusion.name=none", "fusion.name=linear"]  # not the seed
    rows, md = report(groups)
    assert rows[0]["mean"] == 25.0 and rows[1]["mean"] == 50.0
    assert rows[1]["difference"] == "+25.00" and rows[1]["test"] == "paired"
    # 4 pairs, all differences positive: 2 of the 16 sign flips are as extreme -> p = 0.125
    assert rows[1]["p_value"] == "0.125"
    assert "(reference)" in md


def test_one_run_per_condition_gets_no_interval_or_p_and_few_pairs_are_said_to_be_few(tmp_path):
    for seed, (a, b) in enumerate([(10, 30), (20, 50), (30, 40)]):
        base = f"seed: {seed}\nagent:\n  name: cem\n"
        _run(tmp_path / "three", f"{seed}", base + "fusion:\n  name: none\n", [1, a])
        _run(tmp_path / "three", f"{seed + 10}", base + "fusion:\n  name: linear\n", [2, b])
    rows, md = report(group_runs(find_runs([tmp_path / "three"])[0]))
    assert rows[1]["p_value"] == "0.250" and rows[1]["test"] == "paired"  # all three pairs agree
    assert "With 3 paired runs the exact sign-flip test cannot give a p below 0.250" in md
    _run(tmp_path / "one", "0", "seed: 0\nfusion:\n  name: none\n", [1, 10])
    _run(tmp_path / "one", "1", "seed: 0\nfusion:\n  name: linear\n", [2, 30])
    rows, md = report(group_runs(find_runs([tmp_path / "one"])[0]))
    assert rows[1]["p_value"] == "" and rows[1]["ci95_low"] == "" and rows[1]["difference"] == "+20.00"
    assert "| none (1 run) | +20.00 | none (1 run) |" in md and "1.000" not in md


def test_permutation_p_values():
    assert permutation_p([1.0, 2.0, 3.0], [1.0, 2.0, 3.0], paired=True) == 1.0
    assert permutation_p([10.0] * 6, [0.0] * 6, paired=True) == pytest.approx(2 / 64)
    assert permutation_p([10.0, 11.0, 12.0, 13.0], [0.0, 1.0, 2.0, 3.0], paired=False) < 0.05


def test_evaluate_runs_writes_csv_markdown_plot_and_reports_crashed_runs(tmp_path):
    _sweep(tmp_path / "sweep")
    out = run_script("evaluate.py", f"runs={tmp_path / 'sweep'}", f"out={tmp_path / 'report'}", timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    report_dir = tmp_path / "report"
    rows = list(csv.DictReader((report_dir / "summary.csv").open()))
    assert [r["condition"] for r in rows] == ["fusion.name=none", "fusion.name=linear"]
    assert (report_dir / "curves.png").stat().st_size > 1000
    assert list((report_dir / "tensorboard").glob("events.out.tfevents.*"))
    assert "left out" in (report_dir / "summary.md").read_text() and "99" in out.stdout
    assert json.loads(out.stdout.strip().splitlines()[-1])["missing"] == 1


def test_unknown_baseline_fails_with_one_line(tmp_path):
    _sweep(tmp_path)
    out = run_script("evaluate.py", f"runs={tmp_path}", "baseline=nothing", timeout=300)
    assert out.returncode == 2 and "baseline='nothing' is not one condition here" in out.stderr
    assert "allowed: none (fusion.name=none); linear (fusion.name=linear)" in out.stderr
    out = run_script("evaluate.py", f"runs={tmp_path}", "baseline=linear", timeout=300)  # no nested quotes
    assert out.returncode == 0, out.stderr
    assert "| fusion.name=linear (reference) |" in (tmp_path / "summary.md").read_text()


def test_reach_times_each_condition_and_counts_never(tmp_path):
    _sweep(tmp_path)
    groups = group_runs(find_runs([tmp_path])[0])
    rows, md = report(groups, reach=35)
    # none ends at 10, 20, 30, 40: only seed 3 reaches 35 (at 2); the others count as last + 1 = 3
    assert rows[0]["reach_never"] == 3 and rows[0]["reach_mean"] == pytest.approx((3 + 3 + 3 + 2) / 4)
    assert rows[1]["reach_never"] == 1 and "to reach 35" in md


def test_a_run_of_several_learners_counts_as_one_seed_per_learner(tmp_path):
    import torch

    from hfrl_torch.common.checkpoint import save_checkpoint

    run = tmp_path / "tamer"
    run.mkdir()
    (run / "config.yaml").write_text("seed: 2\nagent:\n  name: tamer\n")
    (run / "metrics.jsonl").write_text(
        "\n".join(json.dumps({"game": g, "eval/lines_per_game_mean": 0.0}) for g in (1, 2)) + "\n"
    )
    lines = torch.tensor([[1, 5], [2, 7], [0, 3]])
    save_checkpoint(
        run / "checkpoints" / "last.pt",
        domain="tetris",
        agent="tamer",
        config_yaml="",
        payload={"state": {"lines": lines}},
    )
    runs, _ = find_runs([tmp_path])
    assert sorted(int(r.config["seed"]) for r in runs) == [2000, 2001, 2002]
    rows, _ = report(group_runs(runs))
    assert rows[0]["runs"] == 3 and rows[0]["mean"] == pytest.approx(5.0)


def test_a_keepaway_run_counts_one_seed_per_team_over_its_episode_budget(tmp_path):
    import torch

    from hfrl_torch.common.checkpoint import save_checkpoint

    run = tmp_path / "keepers"
    run.mkdir()
    agent = (
        "agent:\n  name: sarsa\n  learners: 2\n  fields_per_learner: 1\n  episodes: 4\n  log_episodes: 2\n"
    )
    (run / "config.yaml").write_text("seed: 1\n" + agent)
    (run / "metrics.jsonl").write_text(
        json.dumps({"axis": "episodes", "episode": 2, "episode_s_mean": 0}) + "\n"
    )
    # field, ordinal, clock at the end, duration (cycles), holds; team 1 played a fifth episode (past budget)
    rows = [
        [0, 0, 50, 50, 0],
        [1, 0, 30, 30, 0],
        [0, 1, 120, 70, 0],
        [1, 1, 90, 60, 0],
        [1, 2, 190, 100, 0],
        [0, 2, 150, 30, 0],
        [0, 3, 250, 100, 0],
        [1, 3, 210, 20, 0],
        [1, 4, 999, 999, 0],
    ]
    state = {"records": {"rows": torch.tensor(rows)}}
    save_checkpoint(
        run / "checkpoints" / "last.pt",
        domain="keepaway",
        agent="sarsa",
        config_yaml="",
        payload={"state": state},
    )
    runs, _ = find_runs([tmp_path])
    assert sorted(int(r.config["seed"]) for r in runs) == [1000, 1001]
    team0 = next(r for r in runs if r.config["seed"] == 1000).rows
    team1 = next(r for r in runs if r.config["seed"] == 1001).rows
    assert [(r["episode"], r["eval/episode_seconds_mean"]) for r in team0] == [(2, 6.0), (4, 6.5)]
    assert [r["eval/episode_seconds_mean"] for r in team1] == [4.5, 6.0]  # episode 5 is past the budget


def test_an_untaught_reference_and_a_taught_condition_share_one_csv(tmp_path):
    """The reference's row has no effort_* columns, the taught one's has: the CSV holds both."""
    from omegaconf import OmegaConf

    from hfrl_torch.experiment.aggregate import aggregate

    for seed in range(2):
        base = f"seed: {seed}\nagent:\n  name: dqn\n"
        _run(tmp_path / "s", f"{seed}", base + "fusion:\n  name: none\n", [1, 2 + seed])
        taught = tmp_path / "s" / f"{seed + 10}"
        _run(tmp_path / "s", f"{seed + 10}", base + "fusion:\n  name: linear\n", [1, 5 + seed])
        effort = {"feedback_events": 40 + seed, "trainer_minutes": 2.0, "weight": 0.5}
        rows = [json.loads(r) | effort for r in (taught / "metrics.jsonl").read_text().splitlines()]
        (taught / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    aggregate(OmegaConf.create({"runs": str(tmp_path / "s"), "out": str(tmp_path / "r")}))
    rows = list(csv.DictReader((tmp_path / "r" / "summary.csv").open()))
    assert [r["condition"] for r in rows] == ["fusion.name=none", "fusion.name=linear"]
    assert rows[0]["effort_feedback_events_last"] == "" and rows[1]["effort_feedback_events_last"] == "40.5"


def test_holm_adjusts_the_family_and_effect_sizes_are_cohens_d():
    assert holm([0.01, 0.04, 0.03]) == pytest.approx(
        [0.03, 0.06, 0.06]
    )  # 3 x 0.01, max(2 x 0.03, .), 1 x 0.04
    assert holm([0.5]) == [0.5] and holm([0.4, 0.9]) == pytest.approx([0.8, 0.9])
    # paired: mean difference 2 over its sd 1 (differences 1, 2, 3)
    assert effect_size([11.0, 12.0, 13.0], [10.0, 10.0, 10.0], paired=True) == pytest.approx(2.0)
    # unpaired: means 2 apart, pooled sd 1
    assert effect_size([1.0, 2.0, 3.0], [3.0, 4.0, 5.0], paired=False) == pytest.approx(-2.0)
    assert math.isnan(effect_size([1.0, 1.0], [0.0, 0.0], paired=True))  # no spread: no d


def test_several_conditions_get_holm_verdicts_and_a_per_seed_csv(tmp_path):
    for seed in range(5):
        base = f"seed: {seed}\nagent:\n  name: cem\n"
        _run(tmp_path, f"a_none{seed}", base + "fusion:\n  name: none\n", [1, 10 + seed])
        _run(tmp_path, f"b_linear{seed}", base + "fusion:\n  name: linear\n", [1, 20 + seed + seed % 2])
        _run(
            tmp_path,
            f"c_annealed{seed}",
            base + "fusion:\n  name: annealed\n",
            [1, 10 + seed + (seed % 3) - 1],
        )
    rows, md = report(group_runs(find_runs([tmp_path])[0]))
    assert rows[0]["condition"] == "fusion.name=none"  # the reference, found first
    linear = next(r for r in rows if r["condition"] == "fusion.name=linear")
    # 2 of 32 sign patterns: p = 0.0625, shown 0.062; Holm doubles the unrounded value
    assert linear["p_value"] == "0.062" and linear["p_holm"] == "0.125"
    assert float(str(linear["effect_size"])) > 10  # every pair +10 or +11: a tiny spread
    assert "Holm's correction for the family" in md
    said = verdicts(rows, "fusion.name=none")
    assert any("p (Holm) = 0.125" in v and "not significantly different" in v for v in said)
    result = aggregate(OmegaConf.create({"runs": str(tmp_path), "out": str(tmp_path / "out")}))
    with open(result["per_seed_csv"]) as f:
        table = list(csv.DictReader(f))
    assert len(table) == 15 and {r["condition"] for r in table} == {g["condition"] for g in rows}
    none = [float(r["value"]) for r in table if r["condition"] == "fusion.name=none"]
    assert none == [10.0, 11.0, 12.0, 13.0, 14.0]


def test_a_scheme_that_fuses_nothing_is_not_labelled_with_a_weight(tmp_path):
    for seed in range(2):
        base = f"seed: {seed}\nagent:\n  name: cem\n"
        _run(tmp_path, f"a{seed}", base + "fusion:\n  name: none\n  weight: trust\n", [1, 10])
        _run(tmp_path, f"b{seed}", base + "fusion:\n  name: linear\n  weight: trust\n", [1, 20])
        _run(tmp_path, f"c{seed}", base + "fusion:\n  name: linear\n  weight: adaptive\n", [1, 30])
    labels = [g.label for g in group_runs(find_runs([tmp_path])[0])]
    assert labels == [
        "fusion.name=none",
        "fusion.name=linear, fusion.weight=trust",
        "fusion.name=linear, fusion.weight=adaptive",
    ]


def test_the_curves_mark_where_the_trainer_left_in_episodes_only(tmp_path):
    """A lifetime run's figure marks the trainer's departure (trainer.leave_after, counted in episodes: one
    CE iteration is one watched game); a departure counted in minutes, or no departure, draws no mark."""
    base = "agent:\n  name: cem\nfusion:\n  name: linear\n"
    _run(tmp_path, "0", "seed: 0\n" + base + "trainer:\n  name: oracle\n  leave_after: 5\n", [1, 2, 3])
    _run(tmp_path, "1", "seed: 1\n" + base + "trainer:\n  name: oracle\n  leave_after: 5\n", [1, 2, 4])
    minutes = "trainer:\n  leave_after: 30\n  leave_unit: minutes\n"
    _run(tmp_path / "m", "0", "seed: 0\n" + base + minutes, [1])
    _run(tmp_path / "n", "0", "seed: 0\n" + base + "trainer:\n  name: none\n", [1])
    assert departures(group_runs(find_runs([tmp_path / "m"])[0])) == []
    assert departures(group_runs(find_runs([tmp_path / "n"])[0])) == []
    left = tmp_path / "left"
    for name in ("0", "1"):
        (left / name).mkdir(parents=True)
        for f in ("config.yaml", "metrics.jsonl"):
            (left / name / f).write_text((tmp_path / name / f).read_text())
    assert departures(group_runs(find_runs([left])[0])) == [5.0]


def test_an_unknown_baseline_names_several_valued_conditions_as_they_are_typed():
    labels = ["fusion.name=none, trainer.leave_after=None", "fusion.name=linear, trainer.leave_after=20"]
    with pytest.raises(ConfigError) as caught:
        baseline_index("nothing", labels)
    assert "allowed: 'none, None' (fusion.name=none, trainer.leave_after=None); 'linear, 20'" in str(
        caught.value
    )
    assert baseline_index("linear, 20", labels) == 1  # as typed, the quotes removed by Hydra
