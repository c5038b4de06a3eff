"""Diagnostic for docs/keepaway.md item 14: Always Hold with the reference's HoldBall side rule.

The reference (BasicPlayer::holdBall) takes the opponent closest to the ball; if it is within
5 m, the ball goes 45 degrees off the line opponent -> me, on the side away from the opponent's
body heading (iSign = -sign(normalize(body_opp - dir(me - opp)))). The simulator instead uses
the nearest taker within 5 m of the holder and the side nearer the ball. This script swaps the
reference rule in (monkeypatched, nothing in the package changes) and plays Always Hold with
the opponent's heading seen

* ``exact``: every cycle, as the simulator's skills see everything;
* ``stale``: one cycle late on every third cycle (a random phase per field), as the reference
  players' see messages arrive every 150 ms;
* ``late``: one cycle late on every cycle.

Prints one JSON line per (preset, view): share of episodes ended within ``--cycles``, their
mean length in seconds and their taken share.

    PYTHONPATH=. python benchmarks/keepaway_holdball_reference.py [--batch 200] [--cycles 600]
"""

from __future__ import annotations

import argparse
import json
import math

import torch

torch.set_num_threads(1)

import hfrl_torch.envs.keepaway.keepers as keepers_mod  # noqa: E402
import hfrl_torch.envs.keepaway.simulator as sim_mod  # noqa: E402
import hfrl_torch.envs.keepaway.takers as takers_mod  # noqa: E402
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawaySimulator  # noqa: E402
from hfrl_torch.envs.keepaway.physics import direction, norm, unit, wrap_angle  # noqa: E402
from hfrl_torch.envs.keepaway.referee import END_TAKEN  # noqa: E402
from hfrl_torch.envs.keepaway.skills import (  # noqa: E402
    HOLD_OPPONENT_RANGE,
    HOLD_SPOT_TOLERANCE,
    choose,
    face_point,
    kick_ball_close_to_body,
)

_SEEN: dict[str, torch.Tensor] = {}


def reference_hold_ball(pos, vel, body, ball_pos, ball_vel, opp_pos, ratio, goal_x, physics):
    """The reference side rule; the opponents' headings come from ``_SEEN["opp_body"]``."""
    opp_body = _SEEN["opp_body"]
    dist = norm(opp_pos - ball_pos.unsqueeze(-2))
    nearest = dist.argmin(-1, keepdim=True)
    near_pos = torch.gather(opp_pos, -2, nearest.unsqueeze(-1).expand(-1, 1, 2)).squeeze(-2)
    near_body = torch.gather(opp_body, -1, nearest).squeeze(-1)
    close = torch.gather(dist, -1, nearest).squeeze(-1) < HOLD_OPPONENT_RANGE
    away = direction(pos - near_pos)
    side = torch.where(wrap_angle(near_body - away) > 0, -1.0, 1.0)  # Trilearn sign(0) = -1
    angle = torch.where(close, wrap_angle(away + side * math.radians(45.0)), body)
    reach = physics.player_size + physics.ball_size + ratio * physics.kickable_margin
    spot = pos + reach * unit(angle)
    kick = kick_ball_close_to_body(pos, vel, body, ball_pos, ball_vel, angle, ratio, physics)
    goal = torch.tensor([goal_x, 0.0], device=pos.device, dtype=pos.dtype).expand_as(pos)
    turn = face_point(pos, vel, body, goal, physics)
    stays = norm((ball_pos + ball_vel) - (pos + vel)) < 0.85 * physics.kickable_distance
    return choose((norm(ball_pos - spot) < HOLD_SPOT_TOLERANCE) & stays, turn, kick)


def install(view: str, batch: int, generator: torch.Generator) -> None:
    """Route the opponents' (possibly late) headings to the reference HoldBall."""
    keeper_commands, taker_commands = sim_mod.keeper_commands, sim_mod.taker_commands
    phase = torch.randint(0, 3, (batch,), generator=generator)
    clock = {"cycle": 0}
    previous: dict[str, torch.Tensor] = {}

    def seen(current: torch.Tensor, key: str) -> torch.Tensor:
        old = previous.get(key, current)
        previous[key] = current.clone()
        if view == "exact":
            return current
        late = torch.ones_like(phase, dtype=torch.bool)
        if view == "stale":
            late = (clock["cycle"] + phase) % 3 == 2
        return torch.where(late.unsqueeze(-1), old, current)

    def keepers(keeper_pos, keeper_vel, keeper_body, taker_pos, taker_body, *args, **kwargs):
        _SEEN["opp_body"] = seen(taker_body, "takers")
        return keeper_commands(keeper_pos, keeper_vel, keeper_body, taker_pos, taker_body, *args, **kwargs)

    def takers(keeper_pos, keeper_body, *args, **kwargs):
        _SEEN["opp_body"] = seen(keeper_body, "keepers")
        clock["cycle"] += 1
        return taker_commands(keeper_pos, keeper_body, *args, **kwargs)

    sim_mod.keeper_commands, sim_mod.taker_commands = keepers, takers
    keepers_mod.hold_ball = takers_mod.hold_ball = reference_hold_ball


def play(preset: str, view: str, batch: int, cycles: int, seed: int) -> dict:
    saved = (sim_mod.keeper_commands, sim_mod.taker_commands, keepers_mod.hold_ball, takers_mod.hold_ball)
    try:
        install(view, batch, torch.Generator().manual_seed(seed + 1))
        sim = KeepawaySimulator(batch, KeepawayConfig(preset=preset), seed=seed)
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
    finally:
        sim_mod.keeper_commands, sim_mod.taker_commands, keepers_mod.hold_ball, takers_mod.hold_ball = saved
    done = ended.nonzero().squeeze(-1)
    return {
        "preset": preset,
        "view": view,
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
    parser.add_argument("--views", nargs="+", default=["exact", "stale", "late"])
    args = parser.parse_args()
    for preset in args.presets:
        for view in args.views:
            print(json.dumps(play(preset, view, args.batch, args.cycles, args.seed)), flush=True)


if __name__ == "__main__":
    main()
