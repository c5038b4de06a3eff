"""Where a whole keepaway cycle's time goes: perf samples of the compiled kernels, by function.

Runs the benchmark keepers inside the whole-cycle kernel (``KeepawaySimulator.play_policy``) while
``perf record`` samples the process, and prints one JSON object: the field-cycles/s of the sampled
run and each function's share of the samples (its own code only; inlined helpers count in their
caller, libm's transcendental functions on their own lines). perf cannot name numba's functions by
itself, so the kernels are compiled afresh into a temporary cache (40-70 s here), which keeps their
object code in memory, and their addresses go into the ``/tmp/perf-PID.map`` that perf reads.

    python benchmarks/keepaway_profile.py [--perception server|exact] [--batch 1024]
        [--policy hand] [--seconds 12] [--threads 1] [--top 20]

Needs Linux perf (Debian's ``linux-perf``); on a VM without hardware counters it samples the
software clock, which is what the numbers in docs/keepaway.md come from.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import pkgutil
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

_CACHE = tempfile.mkdtemp(prefix="keepaway-profile-numba-")
os.environ["NUMBA_CACHE_DIR"] = _CACHE  # before numba is imported: compile afresh, keep the objects

import numba  # noqa: E402
import torch  # noqa: E402

import hfrl_torch.envs.keepaway.compiled as compiled_cycle  # noqa: E402
from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawaySimulator  # noqa: E402

# numba's mangled names: ...8compiled<len><module><len><function>B<n>v<n>...
_NUMBA_NAME = re.compile(r"compiled\d+([a-z_]+)\d+(\w+?)B\d+v\d+")


def kernel_symbols(module: object) -> list[tuple[int, int, str]]:
    """(address, size, name) of every function in the compiled object code of ``module``'s numba
    dispatchers, named by the compiled module and the Python function it was compiled from."""
    rows = set()
    for attr in dir(module):
        dispatcher = getattr(module, attr)
        for compiled in getattr(dispatcher, "overloads", {}).values():
            library = compiled.library
            try:
                obj = library._get_compiled_object()
            except RuntimeError:  # loaded from a cache or not compiled: no object code to read
                continue
            with tempfile.NamedTemporaryFile(suffix=".o") as fh:
                fh.write(obj)
                fh.flush()
                listing = subprocess.run(
                    ["nm", "-S", "--defined-only", fh.name], capture_output=True, text=True, check=True
                ).stdout
            for line in listing.splitlines():
                parts = line.split()
                if len(parts) != 4 or parts[2] not in "tT":
                    continue
                address = library.get_pointer_to_function(parts[3])
                if address:
                    match = _NUMBA_NAME.search(parts[3])
                    name = f"{match.group(1)}.{match.group(2)}" if match else parts[3][:60]
                    rows.add((address, int(parts[1], 16), name))
    return sorted(rows)


def perf_report(data: Path) -> list[tuple[float, str]]:
    """(share in %, symbol) of ``perf record``'s samples in ``data``, largest first."""
    text = subprocess.run(
        [
            "perf",
            "report",
            "-i",
            str(data),
            "--stdio",
            "--no-children",
            "--sort=symbol",
            "--fields=overhead,sym",
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    rows = []
    for line in text.splitlines():
        parts = line.split()
        if len(parts) >= 3 and parts[0].endswith("%") and parts[1] == "[.]":
            rows.append((float(parts[0].rstrip("%")), parts[2]))
    return sorted(rows, reverse=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--perception", default="server", choices=tuple(TASKS))
    parser.add_argument("--preset", default="2005")
    parser.add_argument("--batch", type=int, default=1024)
    parser.add_argument("--policy", default="hand", choices=("hold", "random", "hand"))
    parser.add_argument("--seconds", type=float, default=12.0)
    parser.add_argument("--frequency", type=int, default=4000, help="perf samples per second")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--top", type=int, default=20)
    args = parser.parse_args()
    for name in ("batch", "seconds", "frequency", "threads", "top"):
        if getattr(args, name) <= 0:
            parser.error(f"--{name} must be positive, not {getattr(args, name)}")
    if shutil.which("perf") is None:
        parser.error("perf not found: install Linux perf (Debian: apt-get install linux-perf)")

    torch.set_num_threads(1)
    numba.set_num_threads(args.threads)
    config = KeepawayConfig(kernels="cycle", preset=args.preset, **TASKS[args.perception])
    sim = KeepawaySimulator(args.batch, config, seed=0)
    print(f"compiling the kernels into {_CACHE} (40-70 s) ...", file=sys.stderr, flush=True)
    sim.play_policy(args.policy, episodes_per_field=2, max_cycles=3)

    perf_map = Path(f"/tmp/perf-{os.getpid()}.map")
    # every module of the package: a function's code runs from its own dispatcher's object, which only
    # the module that defines it (or imports it) lists
    modules = [
        importlib.import_module(f"{compiled_cycle.__name__}.{m.name}")
        for m in pkgutil.iter_modules(compiled_cycle.__path__)
    ]
    symbols = sorted({row for module in modules for row in kernel_symbols(module)})
    perf_map.write_text("".join(f"{a:x} {s:x} {n}\n" for a, s, n in symbols))
    data = Path(_CACHE) / "perf.data"
    try:
        perf = subprocess.Popen(
            [
                *("perf", "record", "-q", "-F", str(args.frequency), "-p", str(os.getpid()), "-o", str(data)),
                *("--", "sleep", str(args.seconds)),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        time.sleep(0.5)  # perf attaches
        cycles, start = 0, time.perf_counter()
        while perf.poll() is None:
            cycles += sim.play_policy(args.policy, episodes_per_field=50, max_cycles=50)[3]
        elapsed = time.perf_counter() - start
        if perf.returncode != 0:
            raise SystemExit(
                f"perf record failed (exit {perf.returncode}); perf_event_paranoid may forbid it"
            )
        shares = perf_report(data)
    finally:
        perf_map.unlink(missing_ok=True)
        shutil.rmtree(_CACHE, ignore_errors=True)

    kernel_names = {name for _, _, name in symbols}
    groups = {"compiled kernels": 0.0, "libm": 0.0, "other": 0.0}
    for share, symbol in shares:
        if symbol in kernel_names:
            groups["compiled kernels"] += share
        elif symbol.startswith(("__", "numba_")) and any(
            f in symbol for f in ("sin", "cos", "atan", "log", "exp", "asin", "tan")
        ):
            groups["libm"] += share
        else:
            groups["other"] += share
    print(
        json.dumps(
            {
                "perception": args.perception,
                "preset": args.preset,
                "batch": args.batch,
                "policy": args.policy,
                "threads": args.threads,
                "field_cycles_per_s": round(cycles / elapsed),
                "groups_percent": {k: round(v, 2) for k, v in groups.items()},
                "top_percent": {symbol: share for share, symbol in shares[: args.top]},
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
