"""Crash safety: random SIGKILLs and resumes, each trial compared with an uninterrupted run.

Three configs, each a tiny run of a few seconds: CE + linear fusion taught by the simulated oracle, TAMER
taught by the simulated oracle, and keepaway Sarsa with linear fusion (the simulated keepaway oracle). For
each, an uninterrupted reference run (run twice: the first fills numba's cache, and the two must agree), then
``--trials`` trials: the run is started, SIGKILLed at a random moment (seeded: uniform between the moment
the reference run wrote its first checkpoint and its end, in wall time), resumed from its last checkpoint,
killed again (1 to
``--max-kills`` kills per trial, drawn), and resumed until it ends. A kill before the first checkpoint leaves
nothing to resume: that attempt's directory is removed and the run started again, as a person would.

Each attempt is a child process forked from this one after every import, running the learner through
``experiment.run.learn`` exactly as ``train.py`` does (the run directory set up by hand: ``resume=`` reads the
same checkpoint), so that a trial costs seconds and not Python's start-up. Every run directory has the same
name, so the feedback sessions (named after it) of a trial and its reference are the same.

Per trial: feedback events lost (in the reference log, not in the trial's), duplicated (the same event id
twice, or a copy the reader drops), extra (in the trial's log, not in the reference's); ``metrics.jsonl``
lines lost and duplicated (wall-time fields left out: ``time/*``, keepaway's ``field_cycles_per_s``); and
whether the final checkpoint's state, policy and curve equal the reference's (its ``resumes`` count left
out). The TAMER loop checkpoints every ``SAVE_EVERY_S`` wall seconds (10 s); the soak sets 0.3 s, so that
kills land between checkpoints. Prints one JSON object::

    nice -n 10 python benchmarks/kill_soak.py --trials 34 --seed 0
"""

from __future__ import annotations

import argparse
import json
import os
import random
import shutil
import signal
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from pathlib import Path
from typing import Any

import numba
import torch
from omegaconf import DictConfig

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.experiment.cli import compose_train
from hfrl_torch.experiment.learners import tetris_games
from hfrl_torch.experiment.registry import learner_for
from hfrl_torch.experiment.run import RunFiles, learn
from hfrl_torch.feedback.log import read_feedback_log

TETRIS = ["domain.width=6", "domain.height=8"]
CONFIGS = {
    "cem+fusion": [
        "agent=cem",
        "fusion=linear",
        "trainer=oracle",
        *TETRIS,
        "agent.population=10",
        "agent.games_per_candidate=2",
        "agent.eval_games=4",
        "agent.watch_pieces=40",
        "agent.iterations=12",
    ],
    "tamer": ["agent=tamer", "trainer=oracle", *TETRIS, "agent.learners=3", "agent.games=15"],
    "keepaway": [
        "domain=keepaway",
        "fusion=linear",
        "agent.learners=2",
        "agent.table_bits=12",
        "agent.log_minutes=0.05",
        "agent.log_episodes=1",
        "agent.hours=0.006",
        "agent.checkpoint_minutes=0.05",
    ],
}
SOAK_SAVE_EVERY_S = 0.3
WALL_KEYS = ("time/", "field_cycles_per_s", "wall_s")
RUN = "run"  # every run directory's name: the feedback sessions are named after it


def _train(cfg: DictConfig, run_dir: Path) -> None:
    """One attempt, as ``train.py`` (``resume=run_dir`` when it holds a checkpoint) runs it."""
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    tetris_games.SAVE_EVERY_S = SOAK_SAVE_EVERY_S
    run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint = load_checkpoint(run_dir) if (run_dir / "checkpoints" / "last.pt").exists() else None
    learner = learner_for(cfg.agent.name, cfg.domain.name)(cfg, run_dir, checkpoint)
    learn(learner, RunFiles(run_dir, cfg))


def spawn(cfg: DictConfig, run_dir: Path) -> int:
    """Fork a child that runs one attempt; its output is discarded, its warnings and errors kept."""
    pid = os.fork()
    if pid:
        return pid
    code = 0
    null = os.open(os.devnull, os.O_WRONLY)
    os.dup2(null, 1)
    os.dup2(null, 2)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            _train(cfg, run_dir)
        with open(run_dir.parent / "warnings.txt", "a") as f:
            f.writelines(f"{w.category.__name__}: {w.message}\n" for w in caught)
    except BaseException:
        with open(run_dir.parent / "errors.txt", "a") as f:
            f.write(traceback.format_exc())
        code = 1
    os._exit(code)


def wait(pid: int, kill_after: float | None, watch: Path | None = None) -> tuple[bool, int, float, float]:
    """Wait for the child; SIGKILL it after ``kill_after`` seconds. Returns whether it was killed, its exit
    status, the seconds it ran and when the file ``watch`` first existed (inf: never)."""
    start, seen = time.perf_counter(), float("inf")
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        elapsed = time.perf_counter() - start
        if watch is not None and seen == float("inf") and watch.exists():
            seen = elapsed
        if done:
            return False, os.waitstatus_to_exitcode(status), elapsed, seen
        if kill_after is not None and elapsed >= kill_after:
            os.kill(pid, signal.SIGKILL)
            os.waitpid(pid, 0)
            return True, -9, elapsed, seen
        time.sleep(0.005)


def metrics(run_dir: Path) -> list[str]:
    """The curve's lines, canonical, without wall-time fields."""
    out = []
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        row = {k: v for k, v in json.loads(line).items() if not k.startswith(WALL_KEYS)}
        out.append(json.dumps(row, sort_keys=True))
    return out


def events(run_dir: Path) -> tuple[list[tuple[Any, ...]], int]:
    """Every logged event (id and content) as read, and the copies the reader dropped."""
    path = run_dir / "feedback.jsonl"
    if not path.exists():
        return [], 0
    contents = read_feedback_log(path)
    if contents.error is not None:
        raise contents.error
    return [(e.session, e.seq, e.time, e.value, e.source, e.step, e.episode) for e in contents.events], (
        contents.duplicates
    )


def same(a: Any, b: Any, where: str = "") -> list[str]:
    """Where two checkpoint values differ (tensors bit for bit, dtype and shape included)."""
    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        ok = (
            isinstance(a, torch.Tensor)
            and isinstance(b, torch.Tensor)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and torch.equal(a, b)
        )
        return [] if ok else [where]
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return [f"{where} keys"]
        return [d for k in a if k != "resumes" for d in same(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        if len(a) != len(b):
            return [f"{where} length"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in same(x, y, f"{where}[{i}]")]
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:  # NaN
        return []
    return [] if a == b else [where]


def final_state(run_dir: Path) -> dict[str, Any]:
    ckpt = load_checkpoint(run_dir)
    history = [{k: v for k, v in r.items() if not k.startswith(WALL_KEYS)} for r in ckpt["history"]]
    return {"state": ckpt["state"], "policy": ckpt["policy"], "history": history}


def trial(
    cfg: DictConfig,
    run_dir: Path,
    reference: Path,
    window: tuple[float, float],
    kills: int,
    rng: random.Random,
) -> dict[str, Any]:
    """Kill the run ``kills`` times at random moments, resume until it ends, compare with ``reference``.

    A fresh run that ends before its first kill (the machine ran faster than for the reference) is started
    again with a new moment drawn before the end it reached, so that every trial is killed at least once."""
    killed = resumed = restarted = redrawn = 0
    while True:
        had_checkpoint = (run_dir / "checkpoints" / "last.pt").exists()
        resumed += had_checkpoint
        pid = spawn(cfg, run_dir)
        kill_after = rng.uniform(*window) if killed < kills else None
        was_killed, code, elapsed, _ = wait(pid, kill_after)
        if not was_killed and killed == 0 and code == 0:
            shutil.rmtree(run_dir)
            window = (min(window[0], 0.5 * elapsed), elapsed)
            redrawn += 1
            resumed -= had_checkpoint
            continue
        if not was_killed:
            break
        killed += 1
        if not (run_dir / "checkpoints" / "last.pt").exists():  # nothing to resume: start again
            shutil.rmtree(run_dir)
            restarted += 1
    ref_events, _ = events(reference)
    got_events, dropped = events(run_dir)
    ids = Counter((e[0], e[1]) for e in got_events)
    ref_lines, got_lines = Counter(metrics(reference)), Counter(metrics(run_dir))
    diff = same(final_state(reference), final_state(run_dir)) if code == 0 else ["(run failed)"]
    notes = run_dir.parent / "warnings.txt"
    return {
        "warnings": notes.read_text().splitlines() if notes.exists() else [],
        "exit": code,
        "kills": killed,
        "resumes": resumed,
        "redrawn": redrawn,
        "restarts_before_first_checkpoint": restarted,
        "events_lost": sum((Counter(ref_events) - Counter(got_events)).values()),
        "events_duplicated": dropped + sum(n - 1 for n in ids.values() if n > 1),
        "events_extra": sum((Counter(got_events) - Counter(ref_events)).values()),
        "events_in_order": got_events == ref_events,
        "metrics_lines_lost": sum((ref_lines - got_lines).values()),
        "metrics_lines_duplicated": sum((got_lines - ref_lines).values()),
        "metrics_identical": metrics(run_dir) == metrics(reference),
        "final_state_identical": not diff,
        "differs_at": diff[:5],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=34, help="trials per config")
    parser.add_argument("--max-kills", type=int, default=3, help="most kills in one trial (drawn 1..max)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the kill moments")
    parser.add_argument("--configs", default=",".join(CONFIGS), help=f"comma-separated, of {list(CONFIGS)}")
    parser.add_argument("--keep", action="store_true", help="keep the run directories (printed)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    rng = random.Random(args.seed)
    root = Path(tempfile.mkdtemp(prefix="kill_soak_"))
    out: dict[str, Any] = {"command": " ".join(sys.argv), "seed": args.seed, "configs": {}}
    started = time.perf_counter()
    for name in args.configs.split(","):
        cfg = compose_train("logger.backend=none", *CONFIGS[name], f"seed={args.seed + 7}")
        walls = []
        for repeat in ("warm-up", "reference"):
            reference = root / f"{name}-{repeat}" / RUN
            _, code, seconds, first = wait(spawn(cfg, reference), None, reference / "checkpoints" / "last.pt")
            if code != 0:
                raise SystemExit(f"{name}: the {repeat} run failed; see {reference.parent / 'errors.txt'}")
            walls.append(seconds)
        wall = walls[-1]
        repeat_diff = same(final_state(root / f"{name}-warm-up" / RUN), final_state(reference))
        repeat_same = not repeat_diff and metrics(root / f"{name}-warm-up" / RUN) == metrics(reference)
        repeat_same = repeat_same and events(root / f"{name}-warm-up" / RUN) == events(reference)
        rows = []
        for i in range(args.trials):
            run_dir = root / f"{name}-{i}" / RUN
            kills = rng.randint(1, args.max_kills)
            rows.append(trial(cfg, run_dir, reference, (min(first, wall), wall), kills, rng))
            if not (args.keep or rows[-1]["differs_at"]):
                shutil.rmtree(run_dir.parent)
        failures = [i for i, r in enumerate(rows) if r["differs_at"] or not r["metrics_identical"]]
        warned = [w for r in rows for w in r["warnings"]]
        out["configs"][name] = {
            "overrides": CONFIGS[name],
            "reference_wall_s": round(wall, 2),
            "warm_up_wall_s": round(walls[0], 2),
            "reference_first_checkpoint_s": round(first, 2),
            "reference_repeat_identical": repeat_same,
            "reference_events": len(events(reference)[0]),
            "reference_metrics_lines": len(metrics(reference)),
            "trials": len(rows),
            "kills": sum(r["kills"] for r in rows),
            "resumes": sum(r["resumes"] for r in rows),
            "redrawn_kill_moments": sum(r["redrawn"] for r in rows),
            "trials_killed": sum(r["kills"] > 0 for r in rows),
            "trials_resumed": sum(r["resumes"] > 0 for r in rows),
            "restarts_before_first_checkpoint": sum(r["restarts_before_first_checkpoint"] for r in rows),
            "failed_runs": sum(r["exit"] != 0 for r in rows),
            "events_lost": sum(r["events_lost"] for r in rows),
            "events_duplicated": sum(r["events_duplicated"] for r in rows),
            "events_extra": sum(r["events_extra"] for r in rows),
            "events_identical_trials": sum(r["events_in_order"] for r in rows),
            "metrics_lines_lost": sum(r["metrics_lines_lost"] for r in rows),
            "metrics_lines_duplicated": sum(r["metrics_lines_duplicated"] for r in rows),
            "metrics_identical_trials": sum(r["metrics_identical"] for r in rows),
            "final_state_identical_trials": sum(r["final_state_identical"] for r in rows),
            "differing_trials": {i: rows[i] for i in failures},
            "warnings": dict(Counter(warned)),
        }
    out["wall_s"] = round(time.perf_counter() - started, 1)
    totals = [c for c in out["configs"].values()]
    out["total"] = {
        k: sum(c[k] for c in totals)
        for k in (
            "trials",
            "trials_killed",
            "trials_resumed",
            "kills",
            "resumes",
            "events_lost",
            "events_duplicated",
            "events_extra",
            "metrics_lines_lost",
            "metrics_lines_duplicated",
            "final_state_identical_trials",
        )
    }
    out["run_dirs"] = str(root) if args.keep or any(c["differing_trials"] for c in totals) else None
    if out["run_dirs"] is None:
        shutil.rmtree(root, ignore_errors=True)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
