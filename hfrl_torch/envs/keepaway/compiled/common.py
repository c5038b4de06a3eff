"""What every part of the compiled keepaway cycle shares: the compile options, the indices of the task's
parameter arrays and of a thread's work arrays, the state as one structure (:class:`CycleState`),
angle and distance helpers and each field's random stream."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np

PI = math.pi
TWO_PI = 2.0 * math.pi
DEG = math.pi / 180.0

# float parameters (prm)
KD, B_DECAY, B_RAND, B_ACC, B_SPEED, B_SIZE = 0, 1, 2, 3, 4, 5
P_DECAY, P_RAND, P_SIZE, P_SPEED, P_ACC, MARGIN = 6, 7, 8, 9, 10, 11
DASH_RATE, KICK_RATE, MIN_DASH, MAX_POWER, KICK_RAND, INERTIA, MAX_MOMENT = 12, 13, 14, 15, 16, 17, 18
LENGTH, WIDTH, DASH_ACC, CRUISE = 19, 20, 21, 22
NUM_PRM = 23
# integer parameters (ip)
N, M, HORIZON, PASSES, TURNOVER, PERIOD = 0, 1, 2, 3, 4, 5
SERVER_PERCEPTION, NOISY_OBS, REFERENCE_HOLD, SERVER_TIMING, NOISE, POLAR = 6, 7, 8, 9, 10, 11
NUM_IP = 12
# per-cycle tables (tabs rows)
T_TRAVEL, T_SERIES, T_CRUISE, T_REACH = 0, 1, 2, 3  # T_REACH..T_REACH + 3: the reach table by turns

# scratch arrays (:func:`scratch`)
S_CMD, S_POS, S_VEL, S_BODY, S_ACC, S_HIT = 0, 1, 2, 3, 4, 5
S_ICYC, S_IPTS, S_TPTS, S_KPOS, S_TPOS, S_ORDER = 6, 7, 8, 9, 10, 11
NO_CAP = 1 << 62  # _intercept searches to its horizon
S_OPEN = 12
# rows of GetOpen's work array (``scr[S_OPEN]`` [6, grid points])
O_TOTAL, O_MINE, O_BLOCKED, O_GX, O_GY, O_HELD = 0, 1, 2, 3, 4, 5

# The helpers skip numba's reference counting (``_nrt=False``; ``_FA`` for the few that allocate):
# a cycle's arrays are borrowed views and its work arrays come from :func:`scratch`, so counting
# them only cost time (a third of a cycle, measured with perf). ``error_model="numpy"``: a division
# by zero gives inf as in torch, and without the Python check the loops vectorise. ``_FI``: the hot
# skills inlined into their callers (a call passes every array field by value): 13 % faster play,
# twice the first compile (22 -> 42 s, once per numba cache).
_F = numba.njit(cache=True, _nrt=False, error_model="numpy")
_FA = numba.njit(cache=True, error_model="numpy")
_FI = numba.njit(cache=True, _nrt=False, error_model="numpy", inline="always")
_PAR = numba.njit(cache=True, nogil=True, parallel=True)  # the entry points: fields split over threads


class CycleState(NamedTuple):
    """The simulator state's arrays (``KeepawayState``'s tensors as numpy views, the same names), passed
    to the compiled code as one structure: B fields, O = 1 + n + m objects (the ball first), P = n + m
    players; the beliefs have P = 0 rows under exact perception."""

    pos: np.ndarray  # [B, O, 2] float32
    vel: np.ndarray  # [B, O, 2] float32
    body: np.ndarray  # [B, O] float32
    counter: np.ndarray  # [B] the takers' possession counter
    episode_cycles: np.ndarray  # [B]
    last_decision: np.ndarray  # [B, n] episode cycle of each keeper's last decision (-1 none)
    prev_holder: np.ndarray  # [B] last cycle's kicking holder (-1 none)
    pass_target: np.ndarray  # [B] the holder's pass target (-1 HoldBall)
    action_start: np.ndarray  # [B] episode cycle of the holder's decision
    clock: np.ndarray  # [B] server cycles
    see_phase: np.ndarray  # [B, P]
    seen_pos: np.ndarray  # [B, P, O, 2] each player's belief
    seen_vel: np.ndarray  # [B, P, O, 2]
    seen_body: np.ndarray  # [B, P, O]


@_F
def _wrap(a: float) -> float:
    x = a + PI
    return x - np.floor(x / TWO_PI) * TWO_PI - PI


@_F
def _hyp(x: float, y: float) -> float:
    return np.sqrt(x * x + y * y)


@_F
def _next(rng: np.ndarray, b: int) -> float:
    """A uniform in [0, 1) with 24 random bits from field ``b``'s splitmix64 generator."""
    z = rng[b] + np.uint64(0x9E3779B97F4A7C15)
    rng[b] = z
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    z = z ^ (z >> np.uint64(31))
    return np.float64(z >> np.uint64(40)) * (1.0 / 16777216.0)


@_F
def uniform_count(ip: np.ndarray) -> int:
    """Uniforms one field draws in a cycle: kick noise [P, 2], turn noise [P], movement noise
    [O, 2], withheld see information [P, O]."""
    players = ip[N] + ip[M]
    count = 0
    if ip[NOISE] != 0:
        count += 2 * players + players + 2 * (players + 1)
    if ip[SERVER_PERCEPTION] != 0:
        count += players * (players + 1)
    return count


@_F
def _fill(rng, b, u):
    for i in range(u.shape[0]):
        u[i] = _next(rng, b)


@_FA
def view_work(ip, features):
    """The work arrays of a kernel that computes a holder's observation, made once per range: its view
    (keepers [n, 2], takers [m, 2]), its teammate order [n - 1] and its state variables [features]."""
    n, m = ip[N], ip[M]
    return np.empty((n, 2)), np.empty((m, 2)), np.empty(n - 1, dtype=np.int64), np.empty(features)


@_FA
def scratch(ip, grid):
    """One thread's work arrays for :func:`_cycle`, made once per range of a kernel call (indices ``S_*``):
    commands [P, 3], new positions, velocities and bodies, accelerations, collisions, the keepers'
    interception cycles and points, the takers' points, a holder's view and teammate order, and
    GetOpen's rows (``O_*``), its grid's x and y among them (contiguous: its loops vectorise, 5x
    faster than strided). Passed down whole only once per cycle: numba copies a tuple's every
    array into each call."""
    n, m = ip[N], ip[M]
    players = n + m
    objects = 1 + players
    opn = np.zeros((6, grid.shape[0]))
    opn[O_GX] = grid[:, 0]
    opn[O_GY] = grid[:, 1]
    return (
        np.empty((players, 3)),
        np.empty((objects, 2)),
        np.empty((objects, 2)),
        np.empty(objects),
        np.empty((objects, 2)),
        np.empty(objects, dtype=np.bool_),
        np.empty(n, dtype=np.int64),
        np.empty((n, 2)),
        np.empty((m, 2)),
        np.empty((n, 2)),
        np.empty((m, 2)),
        np.empty(max(n - 1, 1), dtype=np.int64),
        opn,
    )
