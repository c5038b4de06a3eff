"""Microseconds per call of the keepaway learner's hot calls, torch and numba side by side in one run.

``decide`` of M rows (3v2 keepaway: 13 state variables, 3 actions, 32 tilings, 2^20 weights per table, ten
tables shared by the rows as ``fields_per_learner`` does), at lambda 0 (the thesis) and 0.9; H^'s
``values`` and a ``give`` that credits every row. Each figure is the best of ``--repeats`` blocks of calls
in process CPU time (the machine is shared: the best block is the least disturbed, and time spent
descheduled is not counted), one torch and one numba thread. ``--thread-rows`` also times the compiled
``decide`` of that many rows on one and on two numba threads (wall time: the second thread's work is
process time too), 30 tables as in a run of 10 learners::

    python benchmarks/sarsa_decide.py [--rows 1 10 100 1000] [--repeats 5] [--thread-rows 267]
"""

from __future__ import annotations

import argparse
import json
import time
from collections.abc import Callable

import numba
import torch

from hfrl_torch.agents.sarsa import SarsaLambda, SarsaLambdaNumba
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.models.tile_coding import TileCoding, keepaway_tile_widths

TABLES = 10
WIDTHS = keepaway_tile_widths()


def best_microseconds(call: Callable[[int], object], calls: int, repeats: int) -> float:
    """The fastest block's microseconds per call of ``call(i)``, after one warm-up block."""
    for i in range(calls):
        call(i)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        for i in range(calls):
            call(i)
        best = min(best, (time.process_time() - t0) / calls)
    return best * 1e6


def decide_case(cls: type[SarsaLambda], m: int, lambda_: float, repeats: int) -> float:
    """Microseconds per ``decide`` of ``m`` continuing rows."""
    coder = TileCoding(WIDTHS, 3, learners=TABLES)
    agent = cls(coder, lambda_=lambda_, tables=torch.arange(m) % TABLES)
    gen = torch.Generator().manual_seed(0)
    obs = [torch.rand(m, 13, generator=gen) * 15 for _ in range(8)]
    mask = torch.ones(m, 3, dtype=torch.bool)
    rows, reward = torch.arange(m), torch.ones(m)
    calls = max(2, min(200, 1000 // m))
    return best_microseconds(lambda i: agent.decide(rows, obs[i % 8], mask, reward), calls, repeats)


def threads_case(m: int, repeats: int) -> dict[str, float]:
    """Wall microseconds per compiled ``decide`` of ``m`` rows on one and on two numba threads, the runs
    interleaved, on 30 tables (10 learners x 3 keepers) drawn at random, the best of ``repeats``."""
    coder = TileCoding(WIDTHS, 3, learners=30)
    coder.weight.normal_(generator=torch.Generator().manual_seed(2))
    slots = 50 * 30
    agent = SarsaLambdaNumba(coder, epsilon=0.01, tables=torch.arange(slots) % 30)
    gen = torch.Generator().manual_seed(0)
    steps = [
        (
            torch.randperm(slots, generator=gen)[:m],
            torch.rand(m, 13, generator=gen) * 20,
            torch.rand(m, generator=gen),
        )
        for _ in range(40)
    ]
    mask = torch.ones(m, 3, dtype=torch.bool)
    best = {1: float("inf"), 2: float("inf")}
    for _ in range(repeats):
        for threads in (1, 2):
            numba.set_num_threads(threads)
            t0 = time.perf_counter()
            for rows, obs, reward in steps:
                agent.decide(rows, obs, mask, reward)
            best[threads] = min(best[threads], (time.perf_counter() - t0) / len(steps) * 1e6)
    numba.set_num_threads(1)
    return {"rows": m, "one_thread_us": round(best[1], 1), "two_threads_us": round(best[2], 1)}


def tamer_cases(kernels: str, m: int, repeats: int) -> dict[str, float]:
    """Microseconds per H^ ``values`` of ``m`` rows and per ``give`` crediting ``m`` decisions."""
    model = TileCoding(WIDTHS, 3, learners=TABLES)
    tamer = KeeperTamer(model, fields=m, window=None, history=1, kernels=kernels)
    gen = torch.Generator().manual_seed(1)
    tiles = model.tiles(torch.rand(m, 13, generator=gen) * 15)
    owner = torch.arange(m) % TABLES
    tamer.record(torch.ones(m, dtype=torch.bool), owner, tiles[:, 0], torch.zeros(m, dtype=torch.float64))
    feedback, when = torch.ones(m), torch.full((m,), 0.3, dtype=torch.float64)
    calls = max(2, min(200, 1000 // m))
    return {
        "values_us": best_microseconds(lambda i: tamer.values(owner, tiles), calls, repeats),
        "give_us": best_microseconds(lambda i: tamer.give(feedback, when), calls, repeats),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[1, 10, 100, 1000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--thread-rows", type=int, default=0, help="rows of the two-thread comparison (0: none)"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    numba.set_num_threads(1)
    results = []
    for m in args.rows:
        row: dict[str, object] = {"rows": m}
        for lambda_ in (0.0, 0.9):
            t = decide_case(SarsaLambda, m, lambda_, args.repeats)
            n = decide_case(SarsaLambdaNumba, m, lambda_, args.repeats)
            row[f"decide_lambda{lambda_:g}"] = {
                "torch_us": round(t, 1),
                "numba_us": round(n, 1),
                "speedup": round(t / n, 1),
            }
        t, n = tamer_cases("torch", m, args.repeats), tamer_cases("numba", m, args.repeats)
        for key in t:
            row[f"h_hat_{key[:-3]}"] = {
                "torch_us": round(t[key], 1),
                "numba_us": round(n[key], 1),
                "speedup": round(t[key] / n[key], 1),
            }
        results.append(row)
        print(json.dumps(row), flush=True)
    out: dict[str, object] = {"benchmark": "sarsa_decide", "threads": 1, "tables": TABLES, "results": results}
    if args.thread_rows > 0 and numba.config.NUMBA_NUM_THREADS >= 2:
        out["numba_threads"] = threads_case(args.thread_rows, args.repeats)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
