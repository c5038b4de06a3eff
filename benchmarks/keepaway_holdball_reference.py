"""Diagnostic for docs/keepaway.md item 14: Always Hold with either HoldBall rule, under exact and
under server perception.

The reference rule (BasicPlayer::holdBall, ``hold_ball="reference"``) takes the opponent closest to
the ball and puts the ball on the side away from that opponent's body heading. With the heading
known exactly every cycle (``perception="exact"``) keeper and takers lock into a loop in which the
takers only turn; with the players' own world models (``perception="server"``: a see every 150 ms,
so one cycle in three runs on the previous cycle's heading, rounded to a degree) the loop breaks.
The spec's rule (``hold_ball="spec"``: the nearest taker to the holder, the side nearer the ball)
ends under both.

Prints one JSON line per (preset, perception, rule): share of the fields whose first episode ended
within ``--cycles``, their mean length in seconds and their taken share.

    python benchmarks/keepaway_holdball_reference.py [--batch 200] [--cycles 600]
"""

from __future__ import annotations

import argparse
import json

import torch

torch.set_num_threads(1)

from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawaySimulator  # noqa: E402
from hfrl_torch.envs.keepaway.referee import END_TAKEN  # noqa: E402

TIMING = {"exact": "cycle", "server": "server"}  # each perception with its own decision timing


def play(preset: str, perception: str, rule: str, batch: int, cycles: int, seed: int) -> dict:
    config = KeepawayConfig(
        preset=preset, perception=perception, hold_ball=rule, decision_timing=TIMING[perception]
    )
    sim = KeepawaySimulator(batch, config, seed=seed)
    ended = torch.zeros(batch, dtype=torch.bool)
    length = torch.zeros(batch, dtype=torch.long)
    cause = torch.zeros(batch, dtype=torch.long)
    for _ in range(cycles):
        out = sim.step(torch.zeros(batch, dtype=torch.long), active=~ended)
        length = torch.where(out.ended, out.episode_cycles, length)
        cause = torch.where(out.ended, out.end_cause, cause)
        ended |= out.ended
        if bool(ended.all()):
            break
    done = ended.nonzero().squeeze(-1)
    return {
        "preset": preset,
        "perception": perception,
        "hold_ball": rule,
        "fields": batch,
        "ended_share": round(float(ended.double().mean()), 3),
        "mean_s_of_ended": round(float(length[done].double().mean() / 10.0), 3) if len(done) else None,
        "taken_share_of_ended": round(float((cause[done] == END_TAKEN).double().mean()), 3)
        if len(done)
        else None,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=200)
    parser.add_argument("--cycles", type=int, default=600)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--presets", nargs="+", default=["2005", "rcss19"])
    args = parser.parse_args()
    for preset in args.presets:
        for perception in ("exact", "server"):
            for rule in ("spec", "reference"):
                print(
                    json.dumps(play(preset, perception, rule, args.batch, args.cycles, args.seed)), flush=True
                )


if __name__ == "__main__":
    main()
