"""The glue between :class:`KeepawaySimulator` and the compiled cycle's entry points (kernels.py): the
task's constants as arrays, one random stream per field, and the state's tensors as one
:class:`CycleState` of numpy views the kernels update in place (``kernels="cycle"``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from hfrl_torch.common.threads import thread_count
from hfrl_torch.envs.keepaway.compiled import common as C
from hfrl_torch.envs.keepaway.compiled import kernels as K
from hfrl_torch.envs.keepaway.compiled.common import CycleState
from hfrl_torch.envs.keepaway.compiled.policies import POLICY_CODES
from hfrl_torch.envs.keepaway.params import KeepawayConfig
from hfrl_torch.envs.keepaway.skills import _reach_table, get_open_grid

# Fields a thread needs before a second one gains (a prange region costs 4-11 us here): kernels that play
# cycles (several us a field) split small batches, the per-field bookkeeping (under 1 us a field) only large.
MIN_FIELDS_PER_THREAD = 64
MIN_PLAYING_FIELDS_PER_THREAD = 4


def _parts(batch: int, playing: bool = False) -> int:
    """The field ranges a kernel splits ``batch`` fields into: one per thread (``numba.get_num_threads()``,
    which ``threads=`` sets), fewer where a thread would get under ``MIN_PLAYING_FIELDS_PER_THREAD``
    fields (``playing``: the kernel plays cycles) or ``MIN_FIELDS_PER_THREAD`` fields."""
    return thread_count(batch, MIN_PLAYING_FIELDS_PER_THREAD if playing else MIN_FIELDS_PER_THREAD)


def task_arrays(config: KeepawayConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kernels' float parameters, integer parameters, per-cycle look-ahead tables [7, H + 1]
    (computed in float32 as the torch path does) and GetOpen grid [25, 2]."""
    p = config.physics
    accel = min(p.max_power * p.dash_power_rate, p.player_accel_max)
    cruise = min(accel / (1.0 - p.player_decay), p.player_speed_max)
    prm = np.zeros(C.NUM_PRM)
    for index, value in (
        (C.KD, p.kickable_distance),
        (C.B_DECAY, p.ball_decay),
        (C.B_RAND, p.ball_rand),
        (C.B_ACC, p.ball_accel_max),
        (C.B_SPEED, p.ball_speed_max),
        (C.B_SIZE, p.ball_size),
        (C.P_DECAY, p.player_decay),
        (C.P_RAND, p.player_rand),
        (C.P_SIZE, p.player_size),
        (C.P_SPEED, p.player_speed_max),
        (C.P_ACC, p.player_accel_max),
        (C.MARGIN, p.kickable_margin),
        (C.DASH_RATE, p.dash_power_rate),
        (C.KICK_RATE, p.kick_power_rate),
        (C.MIN_DASH, p.min_dash_power),
        (C.MAX_POWER, p.max_power),
        (C.KICK_RAND, p.kick_rand),
        (C.INERTIA, p.inertia_moment),
        (C.MAX_MOMENT, p.max_moment),
        (C.LENGTH, config.length),
        (C.WIDTH, config.width),
        (C.DASH_ACC, accel),
        (C.CRUISE, cruise),
    ):
        prm[index] = value
    ip = np.zeros(C.NUM_IP, dtype=np.int64)
    for index, value in (
        (C.N, config.keepers),
        (C.M, config.takers),
        (C.HORIZON, config.intercept_horizon),
        (C.PASSES, config.collision_passes),
        (C.TURNOVER, config.turnover),
        (C.PERIOD, config.decision_period_cycles),
        (C.SERVER_PERCEPTION, config.perception == "server"),
        (C.NOISY_OBS, config.noisy_observations),
        (C.REFERENCE_HOLD, config.hold_ball == "reference"),
        (C.SERVER_TIMING, config.decision_timing == "server"),
        (C.NOISE, config.movement_noise),
        (C.POLAR, p.polar_noise),
    ):
        ip[index] = int(value)
    steps = torch.arange(config.intercept_horizon + 1, dtype=torch.float32)
    travel = (1.0 - torch.pow(torch.full_like(steps, p.ball_decay), steps)) / (1.0 - p.ball_decay)
    series = (1.0 - torch.pow(torch.full_like(steps, p.player_decay), steps)) / (1.0 - p.player_decay)
    table = _reach_table(config.intercept_horizon, p, torch.device("cpu"), torch.float32)
    tabs = torch.cat((travel[None], series[None], (steps * cruise)[None], table)).double().numpy()
    grid = get_open_grid(config.length, config.width, torch.device("cpu"), torch.float32).double().numpy()
    return prm, ip, np.ascontiguousarray(tabs), np.ascontiguousarray(grid)


def seed_streams(seed: int, batch: int) -> np.ndarray:
    """One splitmix64 state per field [B] (uint64), hashed from the seed and the field's index so
    that the streams start far apart."""
    mask = (1 << 64) - 1
    out = np.empty(batch, dtype=np.uint64)
    for b in range(batch):
        z = (seed * 0x9E3779B97F4A7C15 + (b + 1) * 0xD1B54A32D192ED03) & mask
        z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & mask
        z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & mask
        out[b] = z ^ (z >> 31)
    return out


@dataclass
class Advance:
    """What an SMDP advance did to each field: cycles simulated and end cause (0 none) [B]."""

    cycles: Tensor
    cause: Tensor


class CompiledCycle:
    """The whole-cycle kernels of one simulator: constants, random streams and numpy views."""

    def __init__(self, config: KeepawayConfig, batch: int, seed: int) -> None:
        self.config = config
        self.prm, self.ip, self.tabs, self.grid = task_arrays(config)
        self.rng = seed_streams(seed, batch)
        self.batch = batch
        self._scratch = (np.zeros(batch, dtype=np.int64), np.zeros(batch, dtype=np.int64))
        self._no_rewards = np.zeros(batch, dtype=np.float32)
        self._no_actions = np.zeros(batch, dtype=np.int64)
        self._no_first = np.zeros(batch, dtype=np.bool_)
        self._views: tuple[object, CycleState] | None = None

    def reseed(self, seed: int) -> None:
        """Restart every field's random stream from ``seed``."""
        self.rng[:] = seed_streams(seed, self.batch)

    def arrays(self, state: object) -> CycleState:
        """The state's tensors as one :class:`CycleState` of numpy views, built once per state object
        (cached while the state object stays the same)."""
        if self._views is not None and self._views[0] is state:
            return self._views[1]
        tensors = [getattr(state, name) for name in CycleState._fields]
        if not all(t.is_contiguous() for t in tensors):
            raise RuntimeError("kernels='cycle' needs contiguous state tensors")
        views = CycleState(*(t.numpy() for t in tensors))
        self._views = (state, views)
        return views

    def forget(self) -> None:
        """Drop the cached views (the state object is about to be replaced)."""
        self._views = None

    def cycle(self, state: object, actions: Tensor, active: Tensor, uniforms: np.ndarray) -> Tensor:
        """One cycle in place on ``state`` with the torch path's uniforms [B, U]; the end causes [B]."""
        cause = torch.zeros(self.batch, dtype=torch.long)
        K.cycle(
            self.arrays(state),
            actions.numpy(),
            active.numpy(),
            uniforms,
            self.prm,
            self.ip,
            self.tabs,
            self.grid,
            cause.numpy(),
            _parts(self.batch, True),
        )
        return cause

    def decisions(self, state: object) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Holder, kickable, must-decide [B] and the holder's state variables [B, F] (float32): the compiled
        decision logic on its own, which the tests hold against the torch path's ``decision``/``observe``."""
        holder = torch.empty(self.batch, dtype=torch.long)
        kickable = torch.empty(self.batch, dtype=torch.bool)
        must = torch.empty(self.batch, dtype=torch.bool)
        obs = torch.empty(self.batch, self.config.num_state_vars, dtype=torch.float32)
        K.decisions(
            self.arrays(state),
            self.prm,
            self.ip,
            holder.numpy(),
            kickable.numpy(),
            must.numpy(),
            obs.numpy(),
            _parts(self.batch),
        )
        return holder, kickable, must, obs

    def observations(self, state: object, decider: Tensor) -> tuple[Tensor, Tensor]:
        """Keeper ``decider`` [B]'s state variables [B, F] (float32) and teammate order [B, n - 1], as
        the compiled cycle numbers the teammates."""
        obs = torch.empty(self.batch, self.config.num_state_vars, dtype=torch.float32)
        order = torch.empty(self.batch, self.config.keepers - 1, dtype=torch.long)
        deciders = decider.to(torch.long).contiguous().numpy()
        K.observations(self.arrays(state), deciders, self.ip, obs.numpy(), order.numpy(), _parts(self.batch))
        return obs, order

    def advance(
        self,
        state: object,
        actions: Tensor,
        first: Tensor,
        running: Tensor,
        sync: str,
        restart: bool,
        max_cycles: int,
    ) -> Advance:
        """Every ``running`` field to its holder's next decision (``sync="all"``: each on its own;
        ``"any"``: in lock-step until one decides or ends), a first cycle with ``actions`` where
        ``first``; in place."""
        cycles = torch.zeros(self.batch, dtype=torch.long)
        cause = torch.zeros(self.batch, dtype=torch.long)
        self._advance(
            state,
            actions.numpy(),
            first.numpy(),
            running.numpy(),
            sync,
            restart,
            max_cycles,
            cycles.numpy(),
            cause.numpy(),
        )
        return Advance(cycles=cycles, cause=cause)

    def _advance(
        self,
        state: object,
        actions: np.ndarray,
        first: np.ndarray,
        running: np.ndarray,
        sync: str,
        restart: bool,
        max_cycles: int,
        cycles: np.ndarray,
        cause: np.ndarray,
    ) -> None:
        """:meth:`advance` on numpy arrays, writing the cycles and end causes into ``cycles``, ``cause``."""
        common = (self.arrays(state), self.rng, actions, first, running)
        tail = (self.prm, self.ip, self.tabs, self.grid, cycles, cause)
        if sync == "all":
            ok = K.advance_fields(*common, restart, max_cycles, *tail, _parts(self.batch, True)) == 0
        else:
            ok = K.advance_any(*common, max_cycles, *tail, _parts(self.batch, True))
        if not ok:
            raise RuntimeError("keepaway: no decision within max_cycles_per_step cycles")

    def env_step(
        self,
        state: object,
        actions: np.ndarray,
        alive: np.ndarray,
        sync: str,
        max_cycles: int,
        outputs: tuple[np.ndarray, ...],
        done: np.ndarray,
        reward: np.ndarray,
    ) -> None:
        """KeepawayEnv's step: the ``alive`` fields advanced with ``actions`` [B] (int64), then the
        outputs, ``done`` and ``reward`` [B] (float32) written in place; two compiled calls."""
        cycles, cause = self._scratch
        self._advance(state, actions, alive, alive, sync, False, max_cycles, cycles, cause)
        self.env_outputs(state, alive, cause, cycles, True, outputs, done, reward)

    def env_reset(
        self,
        state: object,
        mask: np.ndarray,
        to_decision: bool,
        max_cycles: int,
        outputs: tuple[np.ndarray, ...],
        done: np.ndarray,
    ) -> None:
        """KeepawayEnv's reset of the ``mask`` fields: new episodes, with ``to_decision`` run to their
        first decisions (restarting episodes that end before it), and the outputs written in place."""
        cycles, cause = self._scratch
        self.reset(state, mask)
        if to_decision:  # no first cycle, so no actions are read
            self._advance(
                state, self._no_actions, self._no_first, mask, "all", True, max_cycles, cycles, cause
            )
        self.env_outputs(state, mask, cause, cycles, False, outputs, done, self._no_rewards)

    def reset(self, state: object, mask: np.ndarray) -> None:
        """A new episode on the ``mask`` [B] fields (bool numpy), each drawn from its own stream, in
        place; the other fields are untouched."""
        K.reset_fields(self.arrays(state), self.rng, mask, self.prm, self.ip, _parts(self.batch))

    def env_outputs(
        self,
        state: object,
        fields: np.ndarray,
        cause: np.ndarray,
        cycles: np.ndarray,
        stepping: bool,
        outputs: tuple[np.ndarray, ...],
        done: np.ndarray,
        reward: np.ndarray,
    ) -> None:
        """KeepawayEnv's outputs after a step or a reset of ``fields``, in place (see
        ``kernels.env_outputs``; ``outputs`` in the env's ``_OUTPUT_KEYS`` order)."""
        K.env_outputs(
            self.arrays(state),
            fields,
            cause,
            cycles,
            stepping,
            self.prm,
            self.ip,
            *outputs,
            done,
            reward,
            _parts(self.batch),
        )

    def play(
        self, state: object, policy: str, episodes_per_field: int, max_cycles: int
    ) -> tuple[Tensor, Tensor, Tensor, int]:
        """Benchmark keepers ``policy`` on every field up to ``episodes_per_field`` episodes (or
        ``max_cycles`` cycles): durations [B, E], causes [B, E], episodes played [B], field-cycles."""
        if policy not in POLICY_CODES:
            raise ValueError(f"policy={policy!r} is invalid; allowed: {', '.join(POLICY_CODES)}")
        durations = torch.zeros(self.batch, episodes_per_field, dtype=torch.long)
        causes = torch.zeros(self.batch, episodes_per_field, dtype=torch.long)
        played = torch.zeros(self.batch, dtype=torch.long)
        total = K.play(
            self.arrays(state),
            self.rng,
            POLICY_CODES[policy],
            max_cycles,
            durations.numpy(),
            causes.numpy(),
            played.numpy(),
            self.prm,
            self.ip,
            self.tabs,
            self.grid,
            _parts(self.batch, True),
        )
        return durations, causes, played, int(total)

    def uniform_count(self) -> int:
        """Uniforms per field and cycle (see ``common.uniform_count``)."""
        return int(C.uniform_count(self.ip))
