"""Diagnostic for docs/keepaway.md "Fidelity": which part of the server perception changes a benchmark
policy's episodes. Each variant patches one part of ``perception="server"`` (nothing in the package
changes; the patches live in this script) and plays the policy with the reference HoldBall rule and
decision timing. Prints one JSON line per variant.

* ``server``: the option as it is;
* ``unquantised``: see messages report the true state (the timing and the world model stay);
* ``every_cycle``: every player gets a see every cycle (quantised; no cycle runs on extrapolation);
* ``holder_every_cycle``: only the keeper closest to the ball sees every cycle;
* ``holder_ball_blind_exact``: that keeper knows the true ball in the cycles without a see;
* ``holder_players_blind_exact``: ... the true players instead;
* ``others_ball_exact``: every keeper but the one closest to the ball knows the true ball (an upper
  bound on what the say/hear messages, not modelled, could tell them);
* ``opponents_roll_out``: the world model moves unseen opponents with their velocity, like teammates,
  instead of its soccer heuristics (0.3 m towards the ball, 0.25 m along x);
* ``keepers_only`` / ``takers_only``: only one team acts on its world model, the other on the truth.

    python benchmarks/keepaway_perception_parts.py [--policy hand] [--preset rcss19]
        [--episodes 500] [--cap-s 60] [--variants ...]

``--cap-s`` cuts an episode at that length (counted at it; ``cut_share`` says how many): under the
reference HoldBall rule a few Always Hold episodes never end, and the run would wait for them.
"""

from __future__ import annotations

import argparse
import json

import torch

torch.set_num_threads(1)

import hfrl_torch.envs.keepaway.simulator as sim_mod  # noqa: E402
from hfrl_torch.envs.keepaway import play_benchmark_policy  # noqa: E402
from hfrl_torch.envs.keepaway.perception import own_truth  # noqa: E402
from hfrl_torch.envs.keepaway.records import CYCLES_PER_SECOND  # noqa: E402

VARIANTS = (
    "server",
    "unquantised",
    "every_cycle",
    "holder_every_cycle",
    "holder_ball_blind_exact",
    "holder_players_blind_exact",
    "others_ball_exact",
    "opponents_roll_out",
    "keepers_only",
    "takers_only",
)
ORIGINAL = (
    sim_mod.observe,
    sim_mod.extrapolate,
    sim_mod.sees_now,
    sim_mod.KeepawaySimulator._updated_beliefs,
)


def _truth(pos: torch.Tensor, vel: torch.Tensor, body: torch.Tensor) -> tuple[torch.Tensor, ...]:
    players = pos.shape[1] - 1
    return (
        pos.unsqueeze(1).expand(-1, players, -1, -1),
        vel.unsqueeze(1).expand(-1, players, -1, -1),
        body.unsqueeze(1).expand(-1, players, -1),
    )


def _holder_mask(sim: sim_mod.KeepawaySimulator, pos: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """[B, P]: the keeper closest to the ball."""
    n = sim.config.keepers
    holder = (pos[:, 1 : 1 + n] - pos[:, :1]).norm(dim=-1).argmin(-1)
    mask = torch.zeros(like.shape, dtype=torch.bool)
    mask[torch.arange(mask.shape[0]), holder] = True
    return mask


def install(variant: str) -> None:
    """Patch the simulator for ``variant``."""
    _, extrapolate, sees_now, updated = ORIGINAL
    if variant == "unquantised":

        def exact_observe(pos, vel, body, prior_pos, prior_vel, prior_body, keepers, physics, uniforms=None):
            return own_truth(*_truth(pos, vel, body), pos, vel, body)

        sim_mod.observe = exact_observe
    elif variant == "every_cycle":
        sim_mod.sees_now = lambda clock, phase: torch.ones_like(phase, dtype=torch.bool)
    elif variant == "opponents_roll_out":

        def rolling(pos, vel, body, kick_accel, kicked, keepers, physics):
            new_pos, new_vel, new_body = extrapolate(pos, vel, body, kick_accel, kicked, keepers, physics)
            players = pos[:, :, 1:] + vel[:, :, 1:]
            return (
                torch.cat((new_pos[:, :, :1], players), 2),
                torch.cat((new_vel[:, :, :1], vel[:, :, 1:] * physics.player_decay), 2),
                new_body,
            )

        sim_mod.extrapolate = rolling
    elif variant != "server":

        def patched(self, s, cmd, pos, vel, body, clock):
            if variant == "holder_every_cycle":
                holder = _holder_mask(self, pos, s.see_phase)
                sim_mod.sees_now = lambda c, phase: sees_now(c, phase) | holder
                try:
                    return updated(self, s, cmd, pos, vel, body, clock)
                finally:
                    sim_mod.sees_now = sees_now
            b_pos, b_vel, b_body = (t.clone() for t in updated(self, s, cmd, pos, vel, body, clock))
            t_pos, t_vel, t_body = _truth(pos, vel, body)
            n = self.config.keepers
            if variant in ("keepers_only", "takers_only"):
                team = slice(n, None) if variant == "keepers_only" else slice(0, n)
                b_pos[:, team], b_vel[:, team], b_body[:, team] = (
                    t_pos[:, team],
                    t_vel[:, team],
                    t_body[:, team],
                )
                return b_pos, b_vel, b_body
            holder = _holder_mask(self, pos, s.see_phase)
            if variant == "others_ball_exact":
                others = ~holder
                others[:, n:] = False
                m = others[..., None]
                b_pos[:, :, 0] = torch.where(m, t_pos[:, :, 0], b_pos[:, :, 0])
                b_vel[:, :, 0] = torch.where(m, t_vel[:, :, 0], b_vel[:, :, 0])
                return b_pos, b_vel, b_body
            blind = ~sees_now(clock, s.see_phase) & holder
            objects = slice(0, 1) if variant == "holder_ball_blind_exact" else slice(1, None)
            m = blind[..., None, None]
            b_pos[:, :, objects] = torch.where(m, t_pos[:, :, objects], b_pos[:, :, objects])
            b_vel[:, :, objects] = torch.where(m, t_vel[:, :, objects], b_vel[:, :, objects])
            b_body[:, :, objects] = torch.where(
                blind[..., None], t_body[:, :, objects], b_body[:, :, objects]
            )
            return b_pos, b_vel, b_body

        sim_mod.KeepawaySimulator._updated_beliefs = patched


def restore() -> None:
    (sim_mod.observe, sim_mod.extrapolate, sim_mod.sees_now, sim_mod.KeepawaySimulator._updated_beliefs) = (
        ORIGINAL
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="hand", choices=("hold", "random", "hand"))
    parser.add_argument("--preset", default="rcss19")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cap-s", type=float, default=60.0, help="cut episodes at this length (0: never)")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    args = parser.parse_args()
    if args.cap_s < 0:
        parser.error(f"--cap-s {args.cap_s} is invalid: must be 0 (never) or a positive number of seconds")
    for variant in args.variants:
        install(variant)
        try:
            r = play_benchmark_policy(
                args.policy,
                args.episodes,
                preset=args.preset,
                batch=min(args.episodes, 500),
                seed=args.seed,
                progress=False,
                cap_cycles=round(args.cap_s * CYCLES_PER_SECOND) if args.cap_s else None,
                perception="server",
                hold_ball="reference",
                decision_timing="server",
            )
        finally:
            restore()
        keep = ("mean_s", "ci95_low", "ci95_high", "taken_share", "out_share", "cut_share")
        print(
            json.dumps(
                {
                    "variant": variant,
                    "policy": args.policy,
                    "preset": args.preset,
                    **{k: round(r[k], 3) for k in keep if k in r},
                }
            ),
            flush=True,
        )


if __name__ == "__main__":
    main()
