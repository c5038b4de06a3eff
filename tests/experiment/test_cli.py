"""End-to-end smoke runs of train.py and evaluate.py with tiny budgets, and their one-line errors."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
from pathlib import Path

import pytest
import torch
import yaml
from script_runner import run_script

from hfrl_torch.common.checkpoint import checksum
from hfrl_torch.experiment import cli
from hfrl_torch.experiment.config import validate_train
from hfrl_torch.experiment.train import _compare_lines

ROOT = Path(__file__).resolve().parents[2]
TINY = [
    "domain.width=6",
    "domain.height=6",
    "agent.population=8",
    "agent.games_per_candidate=2",
    "agent.eval_games=3",
]


def run(script: str, *args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess:
    """``python <script> <args>`` as a user types it, forked from a process that has made its imports."""
    return run_script(script, *args, cwd=cwd, timeout=300)


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("run") / "r"
    out = run("train.py", *TINY, "agent.iterations=3", "seed=4", f"hydra.run.dir={run_dir}")
    assert out.returncode == 0, out.stderr[-2000:]
    return run_dir


def test_train_writes_config_events_checkpoint_and_tells_where(trained):
    assert (trained / "config.yaml").is_file()
    assert (trained / ".hydra" / "config.yaml").is_file()
    assert list((trained / "tensorboard").glob("events.out.tfevents.*"))
    assert (trained / "checkpoints" / "last.pt").is_file()
    lines = (trained / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["iteration"] for x in lines] == [1, 2, 3]


def test_evaluate_checkpoint_prints_summary_then_json(trained):
    out = run("evaluate.py", f"policy={trained}", "games=5", "seed=1")
    assert out.returncode == 0, out.stderr[-2000:]
    last = json.loads(out.stdout.strip().splitlines()[-1])
    for key in ("domain", "policy", "rules", "board", "games", "mean", "median", "ci95_low", "ci95_high"):
        assert key in last
    assert last["board"] == "6x6" and last["games"] == 5 and last["rules"] == "simplified"
    assert last["ci95_low"] <= last["mean"] <= last["ci95_high"]
    assert "lines per game" in out.stdout


def test_evaluate_reference_policies_with_piece_cap():
    out = run("evaluate.py", "policy=dellacherie", "games=4", "domain.max_pieces=300")
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert (
        res["capped_games"] == 4 and res["pieces_per_game"] == 300
    )  # Dellacherie survives 300 pieces on 10x10
    assert "reached the cap" in out.stdout


def test_resume_continues_and_matches_an_uninterrupted_run(tmp_path):
    whole, part = tmp_path / "whole", tmp_path / "part"
    assert run("train.py", *TINY, "agent.iterations=4", f"hydra.run.dir={whole}").returncode == 0
    assert run("train.py", *TINY, "agent.iterations=2", f"hydra.run.dir={part}").returncode == 0
    out = run("train.py", f"resume={part}", "agent.iterations=4", f"hydra.run.dir={tmp_path / 'resume_log'}")
    assert out.returncode == 0, out.stderr[-2000:]
    a = torch.load(whole / "checkpoints" / "last.pt", weights_only=True)
    b = torch.load(part / "checkpoints" / "last.pt", weights_only=True)
    assert b["state"]["iteration"] == 4
    assert torch.equal(a["state"]["mean"], b["state"]["mean"])
    assert [h["eval/mean_policy_lines_mean"] for h in a["history"]] == [
        h["eval/mean_policy_lines_mean"] for h in b["history"]
    ]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["domain=nosuch"], "unknown domain 'nosuch'; allowed: "),
        (["domain.width=3"], "domain.width=3 is invalid: must be an integer in 4..30"),
        (["nosuchkey=1"], "Could not override 'nosuchkey'"),
    ],
)
def test_bad_input_fails_with_one_clear_line(args, message, tmp_path):
    out = run("train.py", *args, f"hydra.run.dir={tmp_path}")
    assert out.returncode == 2
    err = out.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and message in err[0], out.stderr
    assert not (tmp_path / "checkpoints").exists()


def test_a_sweep_whose_jobs_are_the_same_run_is_refused_before_anything_runs(tmp_path, monkeypatch):
    """fusion=none fuses nothing, so fusion.weight=0.3 and =adaptive are one run twice; launched, the
    duplicates would be counted as two learners by evaluate.py."""
    args = ["-m", "agent=pg", "fusion=none,linear", "fusion.weight=0.3,adaptive", "agent.games=1"]
    out = run("train.py", *args, f"hydra.sweep.dir={tmp_path}")
    err = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(err) == 1, out.stderr
    assert "jobs 0 (" in err[0] and "and 1 (" in err[0] and "fusion=none uses no fusion.weight" in err[0]
    assert not any(tmp_path.iterdir())
    monkeypatch.setenv(cli.CHECKED, "")  # precheck marks the jobs it checked in the environment
    cli.precheck(["-m", "fusion=linear", "fusion.weight=0.3,adaptive"], "train", validate_train)
    assert os.environ[cli.CHECKED] == "1"  # a weight swept over a scheme that uses it: two runs, no error


def test_a_fused_run_ends_with_a_comparison_with_its_parts_that_runs_as_printed(tmp_path):
    """The printed sweep runs the same learner alone and H^ alone beside the fused scheme; evaluate.py then
    pairs them."""
    over = [*TINY, "agent.iterations=2", "fusion=linear", "trainer=oracle", "logger=none"]
    out = run("train.py", *over, f"hydra.run.dir={tmp_path / 'fused'}")
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stderr.splitlines()
    sweep = next(x for x in lines if x.startswith("Compare:")).removeprefix("Compare:").strip()
    where = next(a for a in shlex.split(sweep) if a.startswith("hydra.sweep.dir=")).split("=", 1)[1]
    evaluate = next(x for x in lines if f"evaluate.py runs={where}" in x)
    assert "fusion=none,human_only,linear" in sweep and "the same run beside none and human_only" in evaluate
    args = [
        a for a in shlex.split(sweep)[2:] if not a.startswith("hydra.sweep.dir=")
    ]  # less "python train.py"
    assert args[0] == "-m" and set(over) - {"fusion=linear"} <= set(args)
    swept = run("train.py", *args, f"hydra.sweep.dir={tmp_path / 'compare'}")
    assert swept.returncode == 0, swept.stderr[-2000:]
    ev = run("evaluate.py", f"runs={tmp_path / 'compare'}")
    assert ev.returncode == 0, ev.stderr[-2000:]
    assert all(f"fusion.name={f}" in ev.stdout for f in ("none", "human_only", "linear")), ev.stdout


@pytest.mark.parametrize(
    ("overrides", "parts"),
    [
        (["agent=pg", "fusion=linear"], "fusion=none,linear"),  # PG has no H^-alone condition
        (["domain=keepaway", "fusion=exponential"], "fusion=none,human_only,exponential"),
        (["fusion=none", "trainer=oracle"], None),  # nothing fused: nothing to compare
        (["fusion=linear", "trainer=interactive"], None),  # a person: a sweep cannot run them again
    ],
)
def test_the_comparison_names_only_the_parts_the_agent_has(overrides, parts):
    lines = _compare_lines(cli.compose_train(*overrides), "python", overrides)
    if parts is None:
        assert lines == []
    else:
        assert f" {parts} hydra.sweep.dir=" in lines[0] and lines[0].startswith("Compare:")


def test_corrupt_and_wrong_domain_checkpoints_fail_cleanly(trained, tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes((trained / "checkpoints" / "last.pt").read_bytes()[:100])
    out = run("evaluate.py", f"policy={bad}")
    assert out.returncode == 2 and "is corrupt" in out.stderr and len(out.stderr.strip().splitlines()) == 1
    blob = torch.load(trained / "checkpoints" / "last.pt", weights_only=True)
    blob["domain"] = "keepaway"
    other = tmp_path / "other.pt"
    torch.save(blob, other)  # edited by hand: the checksum no longer matches
    out = run("evaluate.py", f"policy={other}")
    assert (
        out.returncode == 2
        and "fails its checksum" in out.stderr
        and len(out.stderr.strip().splitlines()) == 1
    )
    blob["sha256"] = checksum(blob)  # as a keepaway run would have written it
    torch.save(blob, other)
    out = run("evaluate.py", f"policy={other}")
    assert out.returncode == 2 and "is for domain 'keepaway', not 'tetris'" in out.stderr


def test_tamer_with_a_simulated_oracle_then_evaluate_then_replay_its_log(tmp_path):
    first = tmp_path / "tamer"
    args = ["agent=tamer", "trainer=oracle", "agent.learners=3", "agent.games=2", "domain.height=8"]
    out = run("train.py", *args, f"hydra.run.dir={first}")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "simulated oracle trainer" in out.stderr and "Feedback log:" in out.stderr
    from hfrl_torch.feedback.log import load_feedback_log

    events = load_feedback_log(first / "feedback.jsonl")
    assert events and all(e.source == "simulated:oracle" for e in events)
    assert [json.loads(x)["game"] for x in (first / "metrics.jsonl").read_text().splitlines()] == [1, 2]

    ev = run("evaluate.py", f"policy={first}", "games=3")
    assert ev.returncode == 0, ev.stderr[-2000:]
    assert json.loads(ev.stdout.strip().splitlines()[-1])["features"] == "knox"

    second = tmp_path / "replay"
    rep = [*args[:1], "trainer=replay", f"trainer.log={first / 'feedback.jsonl'}", *args[2:]]
    out = run("train.py", *rep, f"hydra.run.dir={second}")
    assert out.returncode == 0, out.stderr[-2000:]
    replayed = load_feedback_log(second / "feedback.jsonl")
    assert replayed and all(e.source == "replay" for e in replayed)
    assert len(replayed) <= len(events)


def test_resume_refuses_changes_that_redefine_the_run(trained, tmp_path):
    out = run("train.py", f"resume={trained}", "domain.features=dt", "agent.iterations=4")
    assert out.returncode == 2
    assert "domain.features=dt cannot change when resuming" in out.stderr
    allowed = (
        "allowed: agent.iterations, agent.hours, agent.episodes, agent.games, agent.frames, threads, device, "
    )
    allowed += "domain.kernels, agent.kernels, logger.backend"
    assert allowed in out.stderr


def test_keepaway_with_a_simulated_trainer_then_evaluate_its_checkpoint(tmp_path):
    run_dir = tmp_path / "keepaway"
    small = ["agent.learners=2", "agent.table_bits=12", "agent.hours=0.004", "agent.log_minutes=0.1"]
    out = run("train.py", "domain=keepaway", "fusion=linear", *small, f"hydra.run.dir={run_dir}")
    assert out.returncode == 0, out.stderr[-2000:]
    # the choices domain=keepaway and fusion=linear imply, made by the config and named by train.py
    assert "Choices: domain=keepaway agent=sarsa human=tile_coded fusion=linear trainer=oracle" in out.stderr
    assert "events of the simulated oracle trainer (fusion=linear" in out.stderr
    assert f"Curves:           {run_dir / 'metrics.jsonl'}" in out.stderr
    assert f"evaluate.py domain=keepaway policy={run_dir}" in out.stderr
    ev = run("evaluate.py", "domain=keepaway", f"policy={run_dir}", "episodes=8", "domain.batch=4")
    assert ev.returncode == 0, ev.stderr[-2000:]
    result = json.loads(ev.stdout.strip().splitlines()[-1])
    assert result["episodes"] == 8 and result["teams"] == 2 and result["mean_s"] > 0


# ------------------------------------------------------------------ Hydra's own flags


@pytest.mark.parametrize(
    ("args", "expect"),
    [
        (["--cfg", "job"], ["agent:", "name: cem", "trainer:", "name: ${implied_trainer:${fusion.name}}"]),
        (["--cfg", "job", "--resolve", "domain=keepaway", "fusion=linear"], ["name: sarsa", "name: oracle"]),
        (["--cfg", "hydra"], ["run:", "sweep:"]),
        (["--cfg", "all"], ["hydra:", "agent:"]),
        (["--cfg", "job", "--package", "agent", "domain=keepaway"], ["name: sarsa", "alpha: 0.125"]),
        (["--info"], ["Hydra", "Defaults List"]),
        (["--info", "defaults", "domain=keepaway"], ["agent/default_keepaway", "agent/sarsa"]),
        (["--help"], ["== Configuration groups ==", "fusion:", "trainer:"]),
    ],
)
def test_hydras_own_flags_work_as_users_type_them(args, expect, tmp_path):
    out = run("train.py", *args, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    for text in expect:
        assert text in out.stdout, (text, out.stdout[-2000:])
    assert not list(tmp_path.iterdir())  # printing the config writes nothing


def test_cfg_job_resolves_the_choices_the_config_implies():
    out = run("train.py", "--cfg", "job", "--resolve", "domain=keepaway", "trainer=interactive")
    assert out.returncode == 0, out.stderr[-2000:]
    assert "learners: 1" in out.stdout and "decision_period_cycles: 5" in out.stdout
    plain = run("train.py", "--cfg", "job", "--resolve", "domain=keepaway")
    assert "learners: 10" in plain.stdout and "decision_period_cycles: 1" in plain.stdout


def test_a_sweep_with_a_bad_job_stops_before_anything_is_written(tmp_path):
    sweep = tmp_path / "sweep"
    out = run("train.py", "-m", "agent.population=10,1", f"hydra.sweep.dir={sweep}")
    assert out.returncode == 2 and not sweep.exists()
    err = out.stderr.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: job 1 (") and "agent.population=1 is invalid" in err[0]
    out = run("train.py", "-m", "fusion=linear,bogus", f"hydra.sweep.dir={sweep}")
    assert out.returncode == 2 and "unknown fusion 'bogus'" in out.stderr and not sweep.exists()


def test_a_new_run_never_writes_into_an_existing_runs_directory(trained, tmp_path):
    before = (trained / "config.yaml").read_text()
    out = run("train.py", *TINY, "agent.iterations=1", f"hydra.run.dir={trained}")
    assert (
        out.returncode == 2
        and f"{trained} already holds a run; resume it with resume={trained}" in out.stderr
    )
    assert (trained / "config.yaml").read_text() == before
    sweep = tmp_path / "sweep"
    assert (
        run("train.py", "-m", *TINY, "agent.iterations=1", "seed=1,2", f"hydra.sweep.dir={sweep}").returncode
        == 0
    )
    lines = (sweep / "0" / "metrics.jsonl").read_text()
    again = run("train.py", "-m", *TINY, "agent.iterations=1", "seed=1,2", f"hydra.sweep.dir={sweep}")
    assert again.returncode == 2 and "job 0 (" in again.stderr and "already holds a run" in again.stderr
    assert (sweep / "0" / "metrics.jsonl").read_text() == lines  # not appended to


def test_two_runs_started_in_the_same_second_get_their_own_directories(tmp_path):
    from hfrl_torch.experiment.resolvers import run_dir

    first = tmp_path / "10-00-00_tetris_cem"
    assert run_dir(None, str(first)) == str(first)
    first.mkdir()
    assert run_dir(None, str(first)) == f"{first}_2"
    (tmp_path / "10-00-00_tetris_cem_2").mkdir()
    assert run_dir(None, str(first)) == f"{first}_3"
    assert run_dir(str(first), "ignored").startswith(f"{first}/resume-logs/")


def test_a_sweep_job_that_fails_is_reported_and_the_sweep_goes_on(tmp_path):
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        args = ["-m", "trainer=interactive", "trainer.wait_for_page_s=0", f"trainer.port={port},0"]
        out = run("train.py", *args, *TINY, "agent.iterations=1", f"hydra.sweep.dir={tmp_path}")
    assert out.returncode == 1
    assert f"error: cannot serve the browser trainer on 127.0.0.1:{port}" in out.stderr
    assert (tmp_path / "1" / "checkpoints" / "last.pt").exists()  # the job after the failed one ran


def test_an_initial_trust_outside_zero_one_is_refused(tmp_path):
    out = run(
        "train.py",
        "fusion=linear",
        "fusion.weight=trust",
        "fusion.initial_trust=5",
        f"hydra.run.dir={tmp_path / 'r'}",
    )
    assert out.returncode == 2 and "fusion.initial_trust=5 is invalid" in out.stderr
    assert not (tmp_path / "r").exists()


def test_evaluate_help_explains_every_one_of_its_options():
    """Every key of conf/evaluate.yaml (and the domain group) has its line in ``evaluate.py --help``."""
    out = run("evaluate.py", "--help")
    assert out.returncode == 0, out.stderr
    options = {line.split()[0] for line in out.stdout.splitlines() if line.startswith("  ") and line.split()}
    config = yaml.safe_load((ROOT / "conf" / "evaluate.yaml").read_text())
    keys = {k for k in config if k not in ("defaults", "hydra")} | {"domain"}
    assert keys <= options, sorted(keys - options)
