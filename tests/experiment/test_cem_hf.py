"""CE + human feedback (thesis Figure 4.1) through its training loop and through train.py / evaluate.py."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from omegaconf import open_dict
from script_runner import run_script

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment.checks import check_cem
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.experiment.learners.tetris_cem import CEMLearner
from hfrl_torch.experiment.run import RunFiles, learn
from hfrl_torch.feedback.log import load_feedback_log, read_feedback_log

ROOT = Path(__file__).resolve().parents[2]
TINY = [
    "domain.width=6",
    "domain.height=8",
    "agent.population=10",
    "agent.games_per_candidate=2",
    "agent.eval_games=4",
    "agent.watch_pieces=40",
    "logger.backend=none",
]


def _cfg(*overrides: str):
    return compose_config("train", *TINY, *overrides)


def train_cem_hf(cfg, run_dir: Path, checkpoint: dict | None) -> dict:
    """CE + a trainer through train.py's loop (no Hydra run directory)."""
    return learn(CEMLearner(cfg, run_dir, checkpoint), RunFiles(run_dir, cfg))


def _events(run_dir: Path) -> list[tuple]:
    return [(e.time, e.value, e.step, e.episode) for e in load_feedback_log(run_dir / "feedback.jsonl")]


def _curves(run_dir: Path) -> list[dict]:
    rows = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [{k: v for k, v in r.items() if not k.startswith("time/")} for r in rows]


@pytest.mark.parametrize(
    "fusion",
    ["linear", "control_sharing", "linear fusion.weight=adaptive", "linear fusion.weight=bandit"],
)
def test_resumed_run_equals_an_uninterrupted_one(tmp_path, fusion):
    over = ["fusion=" + fusion.split()[0], *fusion.split()[1:], "trainer=oracle", "seed=3"]
    whole, part = tmp_path / "whole", tmp_path / "part"
    whole.mkdir()
    part.mkdir()
    train_cem_hf(_cfg(*over, "agent.iterations=4"), whole, None)
    train_cem_hf(_cfg(*over, "agent.iterations=2"), part, None)
    train_cem_hf(_cfg(*over, "agent.iterations=4"), part, load_checkpoint(part))
    assert _curves(whole) == _curves(part)
    assert _events(whole) == _events(part) and len(_events(whole)) > 10
    a, b = load_checkpoint(whole)["policy"], load_checkpoint(part)["policy"]
    assert torch.equal(a["weights"], b["weights"]) and torch.equal(a["human_weights"], b["human_weights"])


def test_trust_is_updated_by_eq_4_4_from_the_test_lines_and_match_rate(tmp_path):
    over = [
        "fusion=linear",
        "fusion.weight=trust",
        "trainer=oracle",
        "trainer.consistency=0.3",
        "agent.iterations=4",
    ]
    train_cem_hf(_cfg(*over), tmp_path, None)
    rows = _curves(tmp_path)
    assert rows[0]["fusion/weight"] == 0.5  # fusion.initial_trust
    previous = None
    for r in rows:
        w, lines, m = r["fusion/weight"], r["eval/mean_policy_lines_mean"], r["fusion/match_rate"]
        assert 0.0 <= m <= 1.0
        l1 = lines if previous is None else previous  # first update: l1 = l2
        expected = (l1 * w + lines * m) / (l1 + lines) if l1 + lines > 0 else w
        assert r["fusion/weight_next"] == pytest.approx(expected, rel=1e-12)
        previous = lines
    assert len({r["fusion/weight"] for r in rows}) > 1


def test_annealed_weight_decays_by_its_factor_each_iteration(tmp_path):
    train_cem_hf(
        _cfg("fusion=annealed", "fusion.factor=0.5", "trainer=oracle", "agent.iterations=3"), tmp_path, None
    )
    assert [r["fusion/weight"] for r in _curves(tmp_path)] == [1.0, 0.5, 0.25]


@pytest.mark.parametrize(
    ("ranking", "weight", "played"),
    [
        ("fused_while_teaching", "1.0", [None, None, 0.0, 0.0]),
        ("fused_while_teaching", "adaptive", [0.0, None, 0.0, 0.0]),  # fused from the first comparison on
        ("fused", "adaptive", [None] * 4),
        ("alone", "1.0", [0.0] * 4),
    ],
)
def test_candidates_are_ranked_fused_or_on_r_alone_as_agent_rank_candidates_says(
    tmp_path, ranking, weight, played
):
    """agent.rank_candidates: the population plays at weight 0 (on R alone) before the weight rests on
    evidence and after the trainer's last iteration (fused_while_teaching), never (fused: the thesis) or
    always (alone), while the mean policy is still tested at the fusion's weight."""
    over = ["fusion=linear", f"fusion.weight={weight}", "trainer=oracle", "trainer.leave_after=2"]
    cfg = _cfg(*over, "agent.iterations=4", f"agent.rank_candidates={ranking}")
    learner = CEMLearner(cfg, tmp_path, None)
    weights, step = [], learner.cem.step

    def recording_step():
        weights.append(learner.rollout.weight)
        return step()

    learner.cem.step = recording_step
    learn(learner, RunFiles(tmp_path, cfg))
    assert weights == played
    assert learner.rollout.weight is None
    if weight == "1.0":
        assert [r["fusion/weight"] for r in _curves(tmp_path)] == [1.0] * 4
    else:  # the mean policy's first games play the comparison's first arm, before any evidence
        assert _curves(tmp_path)[0]["fusion/weight"] == 1.0
    assert [r["feedback/trainer_present"] for r in _curves(tmp_path)] == [1.0, 1.0, 0.0, 0.0]


@pytest.mark.parametrize("fusion", ["linear", "reward_shaping"])
def test_alone_ranking_searches_as_ce_alone(tmp_path, fusion):
    """agent.rank_candidates=alone: CE's search is CE alone's, draw for draw (the trainer changes only what
    the mean policy plays), so a bad trainer cannot set the search back; with reward shaping the candidates
    are ranked on lines alone."""
    taught = ["fusion=" + fusion.split()[0], *fusion.split()[1:], "trainer=oracle", "trainer.consistency=0.3"]
    learners = {}
    for name, over in {"alone": [], "taught": taught}.items():
        (tmp_path / name).mkdir()
        cfg = _cfg(*over, "agent.iterations=3", "agent.rank_candidates=alone")
        learners[name] = CEMLearner(cfg, tmp_path / name, None)
        learn(learners[name], RunFiles(tmp_path / name, cfg))
    alone, taught = learners["alone"], learners["taught"]
    assert torch.equal(alone.cem.mean, taught.cem.mean) and torch.equal(
        alone.cem.variance, taught.cem.variance
    )
    assert sum(r["feedback/given"] for r in _curves(tmp_path / "taught")) > 0


@pytest.mark.parametrize(("alone", "ranking"), [(True, "fused_while_teaching"), (False, "fused")])
def test_a_saved_config_from_before_rank_candidates_keeps_its_ranking(tmp_path, alone, ranking):
    """A run saved with agent.alone_after_departure (before agent.rank_candidates) is checked and resumed with
    the ranking it meant: fused while the trainer teaches, or always fused."""
    cfg = _cfg("fusion=linear", "trainer=oracle", "agent.iterations=2")
    with open_dict(cfg):
        del cfg.agent["rank_candidates"]
        cfg.agent.alone_after_departure = alone
    check_cem(cfg)
    assert CEMLearner(cfg, tmp_path, None).ranking == ranking
    with open_dict(cfg):
        cfg.agent.alone_after_departure = "sometimes"
    with pytest.raises(ConfigError, match=r"agent\.alone_after_departure"):
        check_cem(cfg)


def _run(script: str, *args: str) -> subprocess.CompletedProcess:
    """``python <script> <args>`` as a user types it, forked from a process that has made its imports."""
    return run_script(script, *args, timeout=300)


def test_train_exponential_then_evaluate_then_replay_the_log(tmp_path):
    run_dir = tmp_path / "exp"
    out = _run(
        "train.py",
        "fusion=exponential",
        "trainer=oracle",
        "agent.iterations=2",
        *TINY,
        f"hydra.run.dir={run_dir}",
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "Done: mean policy" in out.stderr
    ev = _run("evaluate.py", f"policy={run_dir}", "games=4")
    assert ev.returncode == 0, ev.stderr[-2000:]
    res = json.loads(ev.stdout.strip().splitlines()[-1])
    assert "fused with H^ over knox (exponential" in res["features"] and res["board"] == "6x8"

    replay_dir = tmp_path / "replay"
    log = run_dir / "feedback.jsonl"
    out = _run(
        "train.py",
        "fusion=linear",
        "trainer=replay",
        f"trainer.log={log}",
        "agent.iterations=2",
        *TINY,
        f"hydra.run.dir={replay_dir}",
    )
    assert out.returncode == 0, out.stderr[-2000:]
    replayed = load_feedback_log(replay_dir / "feedback.jsonl")
    assert replayed and {e.source for e in replayed} == {"replay"}


def test_killed_run_keeps_every_event_and_resumes(tmp_path):
    """kill -9 mid-run: the log holds every event given before the kill; resume continues it."""
    run_dir = tmp_path / "crash"
    args = ["fusion=linear", "trainer=oracle", "agent.iterations=400", *TINY, f"hydra.run.dir={run_dir}"]
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *args],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    ckpt = run_dir / "checkpoints" / "last.pt"
    deadline = time.time() + 120
    while time.time() < deadline and not (ckpt.exists() and len(_events_or_empty(run_dir)) >= 30):
        time.sleep(0.2)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    before = _events(run_dir)
    assert len(before) >= 30
    done = load_checkpoint(run_dir)["state"]["cem"]["iteration"]
    assert 1 <= done < 400

    out = _run(
        "train.py", f"resume={run_dir}", f"agent.iterations={done + 2}", f"hydra.run.dir={tmp_path / 'r'}"
    )
    assert out.returncode == 0, out.stderr[-2000:]
    after = _events(run_dir)
    assert after[: len(before)] == before and len(after) > len(before)
    assert load_checkpoint(run_dir)["state"]["cem"]["iteration"] == done + 2


def _events_or_empty(run_dir: Path) -> list:
    try:
        return _events(run_dir)
    except Exception:
        return []


def test_a_run_killed_anywhere_resumes_to_the_uninterrupted_run_with_every_event_once(tmp_path):
    """SIGKILL at some moment after the first checkpoint, then resume: the same curve and the same feedback
    log as a run never stopped, no event logged twice, none lost (the checkpoint names the last event its
    learner was given; the trainer gives the ones after it again, matched, not re-written)."""
    over = ["fusion=linear", "trainer=oracle", "seed=5", *TINY]
    whole = tmp_path / "whole"
    out = _run("train.py", *over, "agent.iterations=5", f"hydra.run.dir={whole}")
    assert out.returncode == 0, out.stderr[-2000:]
    run_dir = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), *over, "agent.iterations=5", f"hydra.run.dir={run_dir}"],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    ckpt = run_dir / "checkpoints" / "last.pt"
    deadline = time.time() + 120
    while time.time() < deadline and not ckpt.exists():
        time.sleep(0.05)
    time.sleep(0.15)  # somewhere in the next iteration (or between writes)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    out = _run("train.py", f"resume={run_dir}", f"hydra.run.dir={tmp_path / 'r'}")
    assert out.returncode == 0, out.stderr[-2000:]
    assert _curves(run_dir) == _curves(whole)
    assert _events(run_dir) == _events(whole) and len(_events(whole)) > 10
    assert read_feedback_log(run_dir / "feedback.jsonl").duplicates == 0
