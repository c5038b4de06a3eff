"""Time of every training loop, side by side with another checkout of this project, in one run.

Each loop is one ``train.py`` command with a small budget, run in a fresh process that imports the checkout's
modules first and then times the command itself (config, set-up, the loop, the last checkpoint), so that
Python's start-up is left out. The time is the process's CPU time (``time.process_time``: one thread, so the
work done), which other jobs on the machine disturb far less than wall time; the wall time is kept too.
The two checkouts' runs alternate (A, B, A, B, ...) so that a machine whose speed drifts slows both alike,
and the median of the repeats is reported with the ratio B / A. Both run with one thread
and the same Python (``sys.executable``)::

    git worktree add /tmp/before <commit>
    python benchmarks/loop_speed.py --reference /tmp/before --repeats 3
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LOOPS = {
    "cem": ["agent.iterations=40"],
    # annealed and fixed weights: both checkouts play the same games (the trust factor's match count
    # changed its definition, so its runs differ and their times would not compare)
    "cem+trainer": ["fusion=annealed", "trainer=oracle", "agent.iterations=15"],
    "tamer": ["agent=tamer", "trainer=oracle", "agent.games=8"],
    "qlearning": ["agent=qlearning", "agent.games=200", "agent.eval_games=0"],
    "pg": ["agent=pg", "agent.games=200", "agent.eval_games=0"],
    "pg+trainer": ["agent=pg", "fusion=annealed", "trainer=oracle", "agent.games=150", "agent.eval_games=0"],
    "keepaway": ["domain=keepaway", "agent=sarsa", "human=tile_coded", "agent.hours=0.06"],
    "keepaway+trainer": [
        "domain=keepaway",
        "agent=sarsa",
        "human=tile_coded",
        "fusion=linear",
        "trainer=oracle",
        "agent.hours=0.04",
    ],
}
COMMON = ["logger.backend=none", "threads=1", "seed=0"]
# imports the checkout's modules, then times its train.py as ``python train.py <args>`` would run it
DRIVER = """
import runpy, sys, time
checkout = sys.argv[1]
sys.path.insert(0, checkout)
import hfrl_torch.experiment.train
sys.argv = [checkout + "/train.py", *sys.argv[2:]]
t0, c0 = time.perf_counter(), time.process_time()
try:
    runpy.run_path(checkout + "/train.py", run_name="__main__")
except SystemExit as exit:
    if exit.code:
        raise
print("SECONDS", time.process_time() - c0, time.perf_counter() - t0, file=sys.stderr)
"""


def run_once(checkout: Path, overrides: list[str], out: Path) -> tuple[float, float]:
    """CPU and wall seconds of one ``train.py`` command of ``checkout``, start-up left out (a failed run
    raises)."""
    done = subprocess.run(
        [sys.executable, "-c", DRIVER, str(checkout), *overrides, *COMMON, f"hydra.run.dir={out}"],
        cwd=checkout,
        capture_output=True,
        text=True,
    )
    marks = [line for line in done.stderr.splitlines() if line.startswith("SECONDS ")]
    if done.returncode != 0 or not marks:
        raise RuntimeError(f"{checkout}: train.py {' '.join(overrides)} failed:\n{done.stderr[-2000:]}")
    cpu, wall = marks[-1].split()[1:]
    return float(cpu), float(wall)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--reference", type=Path, required=True, help="the other checkout (A)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--loops", nargs="*", default=list(LOOPS), choices=list(LOOPS))
    args = parser.parse_args()
    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.loops:
            cpu: dict[str, list[float]] = {"reference": [], "this": []}
            wall: dict[str, list[float]] = {"reference": [], "this": []}
            for r in range(args.repeats + 1):  # the first round warms both (numba caches), not counted
                for label, checkout in (("reference", args.reference), ("this", ROOT)):
                    c, w = run_once(checkout, LOOPS[name], Path(tmp) / f"{name}-{label}-{r}")
                    if r > 0:
                        cpu[label].append(c)
                        wall[label].append(w)
            a, b = statistics.median(cpu["reference"]), statistics.median(cpu["this"])
            results[name] = {
                "reference_cpu_s": a,
                "this_cpu_s": b,
                "ratio": b / a,
                "cpu_s": cpu,
                "wall_s": wall,
            }
            print(json.dumps({name: results[name]}), flush=True)
    print(json.dumps({"loops": results}))


if __name__ == "__main__":
    main()
