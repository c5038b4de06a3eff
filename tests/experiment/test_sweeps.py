"""Sweeps: joblib (local parallel) and submitit (its local executor) launchers, an experiment config, and
evaluate.py aggregating what they produce."""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from script_runner import run_script

ROOT = Path(__file__).resolve().parents[2]
TINY = [
    "domain.width=6",
    "domain.height=8",
    "agent.population=10",
    "agent.games_per_candidate=1",
    "agent.eval_games=2",
    "agent.iterations=2",
    "logger.backend=none",
]


def _run(script: str, *args: str, fresh: bool = False) -> subprocess.CompletedProcess:
    """``python <script> <args>`` as a user types it, forked from a process that has made its imports;
    ``fresh``: in a new interpreter (joblib's loky workers take minutes to start from a forked child)."""
    if not fresh:
        return run_script(script, *args, timeout=600)
    return subprocess.run(
        [sys.executable, str(ROOT / script), *args], cwd=ROOT, capture_output=True, text=True, timeout=600
    )


def test_joblib_multirun_is_aggregated_into_the_expected_table(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_joblib_launcher", reason="the sweep extra is not installed")
    sweep = tmp_path / "sweep"
    out = _run(
        "train.py",
        "-m",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        "fusion=none,linear",
        "trainer=oracle",
        "seed=0,1",
        *TINY,
        f"hydra.sweep.dir={sweep}",
        fresh=True,
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2", "3"]
    (sweep / "3" / "metrics.jsonl").unlink()  # a member that crashed before its first iteration
    agg = _run("evaluate.py", f"runs={sweep}", f"out={tmp_path / 'report'}")
    assert agg.returncode == 0, agg.stderr[-3000:]
    rows = list(csv.DictReader((tmp_path / "report" / "summary.csv").open()))
    assert [(r["condition"], r["runs"], r["seeds"]) for r in rows] == [
        ("fusion.name=none", "2", "0 1"),
        ("fusion.name=linear", "1", "0"),
    ]
    assert rows[1]["test"] == "unpaired"
    assert "left out" in agg.stdout and str(sweep / "3") in agg.stdout


def test_submitit_launcher_runs_with_its_local_executor(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="the sweep extra is not installed")
    sweep = tmp_path / "sweep"
    out = _run(
        "train.py",
        "-m",
        "hydra/launcher=submitit_local",
        "hydra.launcher.timeout_min=5",
        "seed=0,1",
        *TINY,
        f"hydra.sweep.dir={sweep}",
    )
    assert out.returncode == 0, out.stderr[-3000:]
    for job in ("0", "1"):
        assert len((sweep / job / "metrics.jsonl").read_text().splitlines()) == 2


SMALL = ["domain.width=6", "domain.height=8", "logger.backend=none"]
EXPERIMENTS = {
    "fig3_3": (False, ["agent.games=1", "agent.learners=2"], "Done: game 1"),
    "fig3_4": (False, ["agent.games=2", "agent.learners=2", "agent.eval_games=1"], "Done: game 2"),
    "fig3_5": (False, ["agent.games=2", "agent.learners=2", "agent.eval_games=1"], "Done: game 2"),
    "fig3_6": (True, [*TINY[2:], "seed=0"], "Done: mean policy"),
    "fig4_1": (True, [*TINY[2:], "seed=0"], "Done: mean policy"),
    "fig4_2": (True, ["agent.games=2", "agent.learners=2", "agent.eval_games=1"], "Done: game 2"),
}


@pytest.mark.parametrize("name", sorted(EXPERIMENTS))
def test_each_thesis_experiment_config_composes_and_runs_tiny(tmp_path, name):
    sweep, extra, done = EXPERIMENTS[name]
    where = f"hydra.sweep.dir={tmp_path}" if sweep else f"hydra.run.dir={tmp_path}"
    args = ["-m"] if sweep else []
    out = _run("train.py", *args, f"+experiment={name}", *SMALL, *extra, where)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stderr.count(done) == (3 if name in ("fig4_1", "fig4_2") else 1)


def test_optuna_sweeper_searches_the_fusion_weight(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="the sweep extra is not installed")
    out = _run(
        "train.py",
        "-m",
        "hydra/sweeper=fusion_weight",
        "hydra.sweeper.n_trials=2",
        "fusion=linear",
        "trainer=oracle",
        *TINY,
        f"hydra.sweep.dir={tmp_path / 'opt'}",
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert "Best parameters: {'fusion.weight':" in out.stdout + out.stderr


def test_the_keepaway_experiment_config_sweeps_its_conditions(tmp_path):
    out = _run(
        "train.py",
        "-m",
        "+experiment=fig5_7",
        "fusion=none,exponential",
        "human.credit=gamma",
        "agent.learners=2",
        "agent.episodes=2",
        "agent.log_episodes=1",
        "agent.table_bits=12",
        f"hydra.sweep.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stderr.count("events of the simulated oracle trainer") == 2
    assert (tmp_path / "0" / "feedback.jsonl").exists() and (
        tmp_path / "1" / "checkpoints" / "last.pt"
    ).exists()


def test_a_sweep_over_four_fusion_schemes_runs_four_keepaway_jobs_with_their_implied_choices(tmp_path):
    out = _run(
        "train.py",
        "-m",
        "domain=keepaway",
        "fusion=none,linear,exponential,human_only",
        "agent.learners=1",
        "agent.hours=0.002",
        "agent.table_bits=12",
        "agent.log_minutes=0.05",
        "logger=none",
        f"hydra.sweep.dir={tmp_path}",
    )
    assert out.returncode == 0, out.stderr[-3000:]
    configs = [OmegaConf.load(tmp_path / str(i) / "config.yaml") for i in range(4)]
    assert [c.fusion.name for c in configs] == ["none", "linear", "exponential", "human_only"]
    assert {c.agent.name for c in configs} == {"sarsa"} and {c.human.name for c in configs} == {"tile_coded"}
    # the trainer each scheme implies, inside the sweep: none for fusion=none, the simulated oracle otherwise
    assert [c.trainer.name for c in configs] == ["none", "oracle", "oracle", "oracle"]
    assert [c.domain.decision_period_cycles for c in configs] == [1, 5, 5, 5]
    assert [(tmp_path / str(i) / "feedback.jsonl").exists() for i in range(4)] == [False, True, True, True]
