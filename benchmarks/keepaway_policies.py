"""Mean episode duration (95 % interval), taken and out shares of the three benchmark keeper
policies in both presets. Prints one JSON list. The task options default to the domain config's
(server perception, the reference HoldBall rule and decision timing); ``--perception exact
--hold-ball spec --decision-timing cycle`` is the exact-state task. An episode still running at
``--cap-s`` simulated seconds (300, as ``evaluate.py``'s ``max_episode_s``) is cut and counted at
that length (``cut_share``): the reference HoldBall rule can hold the ball for good.

    python benchmarks/keepaway_policies.py [--episodes 1000] [--batch 500] [--perception exact|server]
        [--cap-s 300]
"""

from __future__ import annotations

import argparse
import json

import torch

torch.set_num_threads(1)

from hfrl_torch.envs.keepaway import play_benchmark_policy  # noqa: E402
from hfrl_torch.envs.keepaway.benchmark_policies import CYCLES_PER_SECOND  # noqa: E402
from hfrl_torch.envs.keepaway.params import DECISION_TIMINGS, HOLD_RULES, PERCEPTIONS  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--batch", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--presets", nargs="+", default=["2005", "rcss19"])
    parser.add_argument("--policies", nargs="+", default=["hold", "random", "hand"])
    parser.add_argument("--progress", action="store_true")
    parser.add_argument("--perception", default="server", choices=PERCEPTIONS)
    parser.add_argument("--hold-ball", default="reference", choices=HOLD_RULES)
    parser.add_argument("--decision-timing", default="server", choices=DECISION_TIMINGS)
    parser.add_argument("--cap-s", type=float, default=300.0)
    args = parser.parse_args()
    if not args.cap_s > 0:
        parser.error(f"--cap-s {args.cap_s} is invalid: must be a positive number of simulated seconds")
    task = {
        "perception": args.perception,
        "hold_ball": args.hold_ball,
        "decision_timing": args.decision_timing,
    }
    results = []
    for preset in args.presets:
        for policy in args.policies:
            r = play_benchmark_policy(
                policy,
                args.episodes,
                preset=preset,
                batch=args.batch,
                seed=args.seed,
                progress=args.progress,
                cap_cycles=round(args.cap_s * CYCLES_PER_SECOND),
                **task,
            )
            results.append({k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()})
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
