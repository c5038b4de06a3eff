"""Ablations of docs/keepaway.md "Fidelity": the benchmark policies and the Sarsa keepers' learning
curve under one choice of the simulator's and the learner's details. Prints one JSON object.

    python benchmarks/keepaway_fidelity.py policies --preset rcss19 [domain options]
    python benchmarks/keepaway_fidelity.py learn --preset rcss19 [domain and learner options]

Domain options are ``KeepawayConfig`` fields (``--perception exact --hold-ball spec
--decision-timing cycle --movement-noise false``); left out, each is the default task's, the one
``train.py domain=keepaway`` plays. ``policies`` plays Always Hold, Random and
Hand-coded (1000 episodes each by default; ``--cap-s`` cuts episodes at that length, for the settings
where they may never end, exact perception with the reference HoldBall rule, and reports the share
cut). ``learn``
runs what ``train.py domain=keepaway agent=sarsa`` runs (the same construction, seeds and curve
windows: 10 learners x 50 fields, 20 hours, one point per simulated hour) and adds the learner
details train.py does not expose: ``--ties first`` (greedy ties go to the lowest action, HoldBall,
instead of a uniform draw; the reference's argmaxQ draws) and ``--initial-q`` (every weight starts at
initial_q / N, so every Q starts at initial_q; the reference starts at 0).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import torch

from hfrl_torch.envs.keepaway import KeepawayConfig
from hfrl_torch.envs.keepaway.benchmark_policies import play_benchmark_policy
from hfrl_torch.envs.keepaway.records import CYCLES_PER_HOUR, CYCLES_PER_SECOND
from hfrl_torch.experiment.cli import compose_train
from hfrl_torch.experiment.registry import learner_for
from hfrl_torch.experiment.run import Interrupt, RunFiles
from hfrl_torch.experiment.run import learn as run_learner

torch.set_num_threads(1)

POINTS_H = (1, 2, 5, 10, 20)


def config_from(args: argparse.Namespace) -> KeepawayConfig:
    return KeepawayConfig(
        preset=args.preset,
        perception=args.perception,
        hold_ball=args.hold_ball,
        decision_timing=args.decision_timing,
        movement_noise=args.movement_noise == "true",
        noisy_observations=args.noisy_observations == "true",
    )


def policies(args: argparse.Namespace) -> dict:
    config = config_from(args)
    out = {}
    for policy in args.policies:
        r = play_benchmark_policy(
            policy,
            args.episodes,
            preset=config.preset,
            batch=args.batch,
            seed=args.seed,
            progress=False,
            cap_cycles=round(args.cap_s * CYCLES_PER_SECOND) if args.cap_s else None,
            **{k: v for k, v in vars(config).items() if k not in ("preset", "keepers", "takers")},
        )
        out[policy] = {k: round(v, 3) if isinstance(v, float) else v for k, v in r.items()}
    return out


def learn(args: argparse.Namespace) -> dict:
    """train.py's Sarsa keepers (its config, construction and seeds) with the learner details above."""
    config = config_from(args)
    overrides = [
        "domain=keepaway",
        "agent=sarsa",
        "logger.backend=none",
        "threads=1",
        f"seed={args.seed}",
        f"agent.learners={args.learners}",
        f"agent.fields_per_learner={args.fields_per_learner}",
        f"agent.hours={args.hours}",
        "agent.log_minutes=60",
        *(
            f"domain.{name}={str(getattr(config, name)).lower()}"
            for name in ("preset", "perception", "hold_ball", "decision_timing", "movement_noise")
        ),
        f"domain.noisy_observations={str(config.noisy_observations).lower()}",
    ]
    cfg = compose_train(*overrides)
    with tempfile.TemporaryDirectory() as run_dir:
        learner = learner_for("sarsa", "keepaway")(cfg, Path(run_dir), None)
        agent = learner.agent_sarsa
        if args.initial_q:
            agent.coder.weight.fill_(args.initial_q / agent.coder.active_tiles)
        agent.ties = args.ties
        start = time.perf_counter()
        run_learner(learner, RunFiles(Path(run_dir), cfg), [], Interrupt())
        wall = time.perf_counter() - start
    curve = {}
    for h in (h for h in POINTS_H if h <= args.hours):
        w = learner.records.time_window((h - 1) * CYCLES_PER_HOUR, h * CYCLES_PER_HOUR)
        curve[str(h)] = (
            None
            if w is None
            else {
                k: round(w[k], 3)
                for k in ("episode_s_mean", "episode_s_ci95_low", "episode_s_ci95_high", "hold_share")
            }
        )
    return {"config": vars(args), "wall_s": round(wall, 1), "curve": curve}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("policies", "learn"))
    task = KeepawayConfig()  # the defaults are train.py domain=keepaway's task, as the library's are
    parser.add_argument("--preset", default=task.preset)
    parser.add_argument("--perception", default=task.perception)
    parser.add_argument("--hold-ball", default=task.hold_ball)
    parser.add_argument("--decision-timing", default=task.decision_timing)
    for flag in ("movement_noise", "noisy_observations"):
        default = str(getattr(task, flag)).lower()
        parser.add_argument(f"--{flag.replace('_', '-')}", default=default, choices=("true", "false"))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--batch", type=int, default=500)
    parser.add_argument("--cap-s", type=float, default=0.0)
    parser.add_argument("--policies", nargs="+", default=["hold", "random", "hand"])
    parser.add_argument("--learners", type=int, default=10)
    parser.add_argument("--fields-per-learner", type=int, default=50)
    parser.add_argument("--hours", type=float, default=20.0)
    parser.add_argument("--ties", default="random", choices=("random", "first"))
    parser.add_argument("--initial-q", type=float, default=0.0)
    args = parser.parse_args()
    if args.cap_s < 0:
        parser.error(f"--cap-s {args.cap_s} is invalid: must be 0 (never) or a positive number of seconds")
    print(json.dumps(policies(args) if args.mode == "policies" else learn(args)))


if __name__ == "__main__":
    main()
