"""Server parameter presets and the task configuration of the keepaway simulator.

Two presets reproduce the rcssserver physics the keepaway benchmark was run on:
``"2005"`` (server 9.4.5, the Adaptive Behavior 2005 papers) and ``"rcss19"``
(current servers). The values follow docs/keepaway.md and the project spec.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import torch

PRESETS = ("2005", "rcss19")


@dataclass(frozen=True)
class PhysicsParams:
    """Server constants of one preset (metres, cycles of 100 ms, angles in radians)."""

    ball_decay: float = 0.94
    ball_rand: float = 0.05
    ball_accel_max: float = 2.7
    ball_speed_max: float = 2.7
    ball_size: float = 0.085
    player_decay: float = 0.4
    player_rand: float = 0.1
    player_size: float = 0.3
    player_speed_max: float = 1.2
    player_accel_max: float = 1.0
    kickable_margin: float = 0.7
    dash_power_rate: float = 0.006
    kick_power_rate: float = 0.027
    min_dash_power: float = -100.0
    max_power: float = 100.0
    kick_rand: float = 0.0
    inertia_moment: float = 5.0
    max_moment: float = math.pi
    polar_noise: bool = False  # False: uniform per axis (server 9); True: polar (rcss19)

    @property
    def kickable_distance(self) -> float:
        """Centre distance within which a player can kick the ball (1.085 m)."""
        return self.player_size + self.kickable_margin + self.ball_size


def physics_preset(name: str) -> PhysicsParams:
    """The physics constants of the named preset (``"2005"`` or ``"rcss19"``)."""
    if name == "2005":
        return PhysicsParams()
    if name == "rcss19":
        return PhysicsParams(
            ball_speed_max=3.0,
            player_speed_max=1.05,
            min_dash_power=0.0,
            kick_rand=0.1,
            polar_noise=True,
        )
    raise ValueError(f"unknown keepaway preset {name!r}; expected one of {PRESETS}")


KERNELS = ("auto", "numba", "torch", "cycle")
PERCEPTIONS = ("exact", "server")
HOLD_RULES = ("spec", "reference")
DECISION_TIMINGS = ("cycle", "server")

# The two tasks' perception options, for ``KeepawayConfig(**TASKS[name])``: "server" is the reference's
# (each player on its own world model, BasicPlayer's HoldBall, the players' decision timing; the default of
# KeepawayConfig and of the domain config), "exact" the true state every cycle with the spec's HoldBall and
# timing (the simulator's only task before these options, and so what a saved task without them played).
TASKS = MappingProxyType(
    {
        "server": MappingProxyType(
            {"perception": "server", "hold_ball": "reference", "decision_timing": "server"}
        ),
        "exact": MappingProxyType({"perception": "exact", "hold_ball": "spec", "decision_timing": "cycle"}),
    }
)


def resolve_kernels(kernels: str, device: torch.device, dtype: torch.dtype = torch.float32) -> str:
    """``"numba"``, ``"torch"`` or ``"cycle"``: how a cycle runs (``"auto"`` is numba for float32 on
    CPU, torch otherwise). ``"numba"`` and ``"torch"`` give the same bits; ``"cycle"`` (whole cycles
    compiled, float32 on CPU) agrees with them within float32 rounding."""
    if kernels not in KERNELS:
        raise ValueError(f"kernels={kernels!r} is invalid; allowed: {', '.join(KERNELS)}")
    fits = device.type == "cpu" and dtype == torch.float32
    if kernels == "auto":
        return "numba" if fits else "torch"
    if kernels in ("numba", "cycle") and not fits:
        raise ValueError(
            f"kernels={kernels!r} runs float32 on the CPU only, not {dtype} on {device}; use kernels='torch'"
        )
    return kernels


@dataclass(frozen=True)
class KeepawayConfig:
    """Everything that defines a keepaway task, apart from the batch size and the seed.

    The defaults are the task ``train.py domain=keepaway`` plays (conf/domain/keepaway.yaml): the 2005
    preset, 3v2 on 20 x 20 m, movement noise, server perception (``TASKS["server"]``); the exact-state
    task is ``KeepawayConfig(**TASKS["exact"])``. Two fields depend on how and by whom the task is run,
    and train.py may pick other values: ``kernels`` (train.py: ``cycle`` on the CPU, ``numba`` for the
    browser trainer, ``torch`` on a GPU) and ``decision_period_cycles`` (train.py: 5 when a trainer
    watches, else 1). A saved task that predates the perception options: :func:`saved_config`.

    :param preset: physics preset, ``"2005"`` or ``"rcss19"``.
    :param keepers: number of keepers n (at least 2).
    :param takers: number of takers m (at least 1).
    :param length: region length L in metres (x extent).
    :param width: region width W in metres (y extent).
    :param turnover_cycles: cycles of taker possession that end an episode; ``None`` means the
        preset's server value (5 for ``"2005"``, 4 for ``"rcss19"``).
    :param movement_noise: add the server's movement, turn and kick noise.
    :param noisy_observations: quantise the deciding keeper's view like the server's visual sensor
        (``perception="exact"`` only).
    :param decision_period_cycles: cycles a HoldBall decision lasts (1 = 100 ms reference,
        5 = 500 ms as in the thesis's human-feedback experiments).
    :param intercept_horizon: look-ahead of GoToBall in cycles.
    :param collision_passes: maximal passes of the collision resolution.
    :param kernels: how a cycle runs, not what it computes: ``"auto"`` (numba for float32 on CPU,
        torch otherwise), ``"numba"`` (GoToBall's and GetOpen's searches and the collision passes
        compiled, the same bits as torch), ``"torch"``, or ``"cycle"`` (whole cycles and the SMDP
        advance compiled per field, float32 on CPU; within float32 rounding of torch).
    :param perception: what the players know: ``"exact"`` (every player sees the true state every
        cycle) or ``"server"`` (the default: each player acts on its own world model, refreshed by the
        server's quantised see message every 150 ms and extrapolated in between, as the UT keepaway
        players' world model does; see perception.py).
    :param hold_ball: HoldBall's opponent and side rule: ``"spec"`` (the nearest taker to the holder,
        the side nearer the ball) or ``"reference"`` (the default; BasicPlayer::holdBall: the opponent
        nearest the ball, the side away from its body heading).
    :param decision_timing: when the keeper with the ball decides: ``"cycle"`` (whenever it truly can
        kick the ball; a pass runs while it stays kickable) or ``"server"`` (the default: when its world
        model says it can kick; a pass is re-decided at each see message and the reward clock restarts
        at every cycle the pass is carried on, as KeepawayPlayer::keeperWithBall does).
    """

    preset: str = "2005"
    keepers: int = 3
    takers: int = 2
    length: float = 20.0
    width: float = 20.0
    turnover_cycles: int | None = None
    movement_noise: bool = True
    noisy_observations: bool = False
    decision_period_cycles: int = 1
    intercept_horizon: int = 30
    collision_passes: int = 10
    kernels: str = "auto"
    perception: str = "server"
    hold_ball: str = "reference"
    decision_timing: str = "server"

    def __post_init__(self) -> None:
        physics_preset(self.preset)
        for name, allowed in (
            ("kernels", KERNELS),
            ("perception", PERCEPTIONS),
            ("hold_ball", HOLD_RULES),
            ("decision_timing", DECISION_TIMINGS),
        ):
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid; allowed: {', '.join(allowed)}")
        if self.noisy_observations and self.perception == "server":
            raise ValueError(
                "noisy_observations=True quantises the exact state's view; perception='server' "
                "quantises every player's sightings already: set noisy_observations=False"
            )
        if self.keepers < 2:
            raise ValueError("keepaway needs at least 2 keepers")
        if self.takers < 1:
            raise ValueError("keepaway needs at least 1 taker")
        if self.decision_period_cycles < 1:
            raise ValueError("decision_period_cycles must be >= 1")
        if self.length <= 0 or self.width <= 0:
            raise ValueError("the region must have a positive size")

    @property
    def sees(self) -> bool:
        """Whether the players' see messages are timed (server perception or decision timing)."""
        return self.perception == "server" or self.decision_timing == "server"

    @property
    def physics(self) -> PhysicsParams:
        """The preset's physics constants."""
        return physics_preset(self.preset)

    @property
    def turnover(self) -> int:
        """Cycles of taker possession that end the episode."""
        if self.turnover_cycles is not None:
            return self.turnover_cycles
        return 5 if self.preset == "2005" else 4

    @property
    def num_actions(self) -> int:
        """HoldBall plus one PassBall per teammate."""
        return self.keepers

    @property
    def num_state_vars(self) -> int:
        """Length of the deciding keeper's state vector, 4n + 2m - 3."""
        return 4 * self.keepers + 2 * self.takers - 3

    def replace(self, **changes: object) -> KeepawayConfig:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


def saved_config(values: Mapping[str, Any]) -> KeepawayConfig:
    """The task a saved config plays (a checkpoint's ``domain_config``, a saved run's ``domain``): its
    fields, and where it predates ``perception``, ``hold_ball`` or ``decision_timing`` the exact task's
    value, which it was trained on (the defaults then), so it replays as it was trained."""
    return KeepawayConfig(**{**TASKS["exact"], **values})
