"""Time of every training loop, side by side with another checkout of this project, in one run.

Each loop is one ``train.py`` command with a small budget, run in a fresh process that imports all of the
checkout's modules first and then times the command itself (config, set-up, the loop, the last
checkpoint), so that Python's start-up and the imports are left out. The time is the process's user CPU
time (``os.times().user``: one thread, so the work done), which other jobs on the machine disturb far
less than wall time; the kernel's time, mostly the feedback log's fsyncs (as many in both), is left out
because it follows the disk's other traffic. The wall time is kept too. The two checkouts' runs alternate
(A, B, A, B, ...) so that a machine whose speed drifts slows both alike. Reported: the ratio B / A of the
medians, of the fastest runs (other load only ever adds time), and the median of each round's own ratio
(its two runs met the same machine). Both run with one thread and the same Python (``sys.executable``)::

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
    "tamer": ["agent=tamer", "trainer=oracle", "agent.games=16"],  # set-up (~0.6 s) a small share
    "qlearning": ["agent=qlearning", "agent.games=200", "agent.eval_games=0"],
    "pg": ["agent=pg", "agent.games=200", "agent.eval_games=0"],
    "pg+trainer": ["agent=pg", "fusion=annealed", "trainer=oracle", "agent.games=150", "agent.eval_games=0"],
    "keepaway": ["domain=keepaway", "agent=sarsa", "human=tile_coded", "agent.hours=0.06"],
    "keepaway+trainer": [
        "domain=keepaway",
        "agent=sarsa",
        "human=tile_coded",
        "fusion=linear",
        "fusion.weight=trust",  # the weight docs/benchmarks.md measured
        "trainer=oracle",
        "agent.hours=0.04",
    ],
}
COMMON = ["logger.backend=none", "threads=1", "seed=0"]
# imports every module of the checkout's package (so that neither side's timing holds imports the other
# made before it: a loop's module may be imported when it is chosen) and sets them aside from the garbage
# collector, then times its train.py as ``python train.py <args>`` would run it
DRIVER = """
import gc, importlib, os, pkgutil, runpy, sys, time
checkout = sys.argv[1]
sys.path.insert(0, checkout)
import hfrl_torch
for module in pkgutil.walk_packages(hfrl_torch.__path__, "hfrl_torch."):
    importlib.import_module(module.name)
gc.collect()
gc.freeze()  # the imported modules' objects: the collector's full passes then scan only what the run makes
sys.argv = [checkout + "/train.py", *sys.argv[2:]]
t0, c0 = time.perf_counter(), os.times().user
try:
    runpy.run_path(checkout + "/train.py", run_name="__main__")
except SystemExit as exit:
    if exit.code:
        raise
print("SECONDS", os.times().user - c0, time.perf_counter() - t0, file=sys.stderr)
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
            fastest_a, fastest_b = min(cpu["reference"]), min(cpu["this"])
            pairs = [b_ / a_ for a_, b_ in zip(cpu["reference"], cpu["this"], strict=True)]
            results[name] = {
                "reference_cpu_s": a,
                "this_cpu_s": b,
                "ratio": b / a,
                "fastest_ratio": fastest_b / fastest_a,
                "paired_ratio": statistics.median(pairs),
                "cpu_s": cpu,
                "wall_s": wall,
            }
            print(json.dumps({name: results[name]}), flush=True)
    print(json.dumps({"loops": results}))


if __name__ == "__main__":
    main()
