"""The numba kernels (CPU fast path) give the torch path's bits: on random scenes, on scenes built
to reach every branch, and over whole simulated episodes."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from typing import Any

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawaySimulator, hand_coded_actions
from hfrl_torch.envs.keepaway.params import physics_preset, resolve_kernels
from hfrl_torch.envs.keepaway.physics import resolve_collisions
from hfrl_torch.envs.keepaway.skills import (
    INTERCEPT_BLOCK,
    get_open_grid,
    get_open_target,
    intercept_estimate,
)

FIELDS = 256


def random_scene(seed: int, players: int, spread: float, fields: int = FIELDS) -> dict[str, torch.Tensor]:
    """Players, ball and velocities of ``fields`` fields drawn from ``seed``; ``spread`` is the
    half size of the square they stand in (small values crowd them together)."""
    g = torch.Generator().manual_seed(seed)

    def uniform(*shape: int, scale: float) -> torch.Tensor:
        return (2 * torch.rand(shape, generator=g) - 1) * scale

    return {
        "pos": uniform(fields, players, 2, scale=spread),
        "vel": uniform(fields, players, 2, scale=0.6),
        "body": uniform(fields, players, scale=math.pi),
        "ball_pos": uniform(fields, 2, scale=spread),
        "ball_vel": uniform(fields, 2, scale=2.5),
    }


def both(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> tuple[Any, Any]:
    """``fn`` with the numba and with the torch kernels."""
    return fn(*args, **kwargs, kernels="numba"), fn(*args, **kwargs, kernels="torch")


def bits(x: torch.Tensor) -> torch.Tensor:
    """The raw bits of a float32 tensor (so +0.0 and -0.0 differ), other tensors as they are."""
    return x.view(torch.int32) if x.dtype == torch.float32 else x


def assert_same_bits(a: tuple | torch.Tensor, b: tuple | torch.Tensor) -> None:
    """Every tensor of ``a`` equals the one of ``b`` bit for bit."""
    for x, y in zip(a, b, strict=True) if isinstance(a, tuple) else [(a, b)]:
        assert x.dtype == y.dtype and x.shape == y.shape
        assert torch.equal(bits(x), bits(y)), (
            f"{int((bits(x) != bits(y)).sum())} of {x.numel()} values differ"
        )


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    preset=st.sampled_from(["2005", "rcss19"]),
    spread=st.sampled_from([3.0, 12.0]),
)
def test_interception_search_matches_torch(seed: int, preset: str, spread: float) -> None:
    s = random_scene(seed, 5, spread)
    physics = physics_preset(preset)
    numba_out, torch_out = both(
        intercept_estimate, s["pos"], s["vel"], s["body"], s["ball_pos"], s["ball_vel"], 30, physics
    )
    assert_same_bits(numba_out, torch_out)


def test_interception_found_and_fallback_alike_beyond_one_block() -> None:
    """More fields than the torch path's CPU block, players both within and beyond the horizon."""
    s = random_scene(7, 5, 12.0, fields=INTERCEPT_BLOCK + 77)
    args = (s["pos"], s["vel"], s["body"], s["ball_pos"], s["ball_vel"], 30, physics_preset("2005"))
    numba_out, torch_out = both(intercept_estimate, *args)
    assert_same_bits(numba_out, torch_out)
    cycles = numba_out[0]
    assert (cycles <= 30).any() and (cycles > 30).any()
    grid = get_open_grid(20.0, 20.0, torch.device("cpu"), torch.float32)
    assert_same_bits(*both(get_open_target, s["pos"][:, :3], s["pos"][:, 3:], s["ball_pos"], grid))


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), keepers=st.integers(2, 5), takers=st.integers(1, 4))
def test_get_open_choice_matches_torch(seed: int, keepers: int, takers: int) -> None:
    s = random_scene(seed, keepers + takers, 10.0)
    grid = get_open_grid(20.0, 20.0, torch.device("cpu"), torch.float32)
    keeper_pos, taker_pos = s["pos"][:, :keepers], s["pos"][:, keepers:]
    assert_same_bits(*both(get_open_target, keeper_pos, taker_pos, s["ball_pos"], grid))


def test_get_open_with_every_cone_blocked_and_ties() -> None:
    grid = get_open_grid(20.0, 20.0, torch.device("cpu"), torch.float32)
    pass_from = torch.tensor([[-50.0, 0.0], [0.0, 0.0]])
    # field 0: a taker between a far passer and the whole grid blocks every cone; field 1: a
    # symmetric scene (ties go to the first grid point)
    takers = torch.tensor([[[-45.0, 0.0], [-40.0, 3.0]], [[0.0, 9.0], [0.0, -9.0]]])
    keepers = torch.tensor([[[1.0, 1.0], [2.0, -1.0]], [[9.0, 0.0], [-9.0, 0.0]]])
    numba_out, torch_out = both(get_open_target, keepers, takers, pass_from, grid)
    assert_same_bits(numba_out, torch_out)
    assert numba_out[0].abs().sum() == 0  # no open point: the region's centre


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), objects=st.integers(2, 10), crowd=st.sampled_from([0.3, 1.0, 3.0]))
def test_collision_passes_match_torch(seed: int, objects: int, crowd: float) -> None:
    s = random_scene(seed, objects, crowd)
    radius = torch.tensor([0.085] + [0.3] * (objects - 1))
    numba_out, torch_out = both(resolve_collisions, s["pos"], s["vel"], radius, 10)
    assert_same_bits(numba_out, torch_out)
    if crowd < 1.0:
        assert numba_out[2].any()


# float32 offsets whose float64-rounded hypot differs from the correctly rounded one (and so
# from torch.hypot's vectorised loop): both paths must use the same hypot
HYPOT_CASES = [
    (0.16723857820034027, -0.19954605400562286),
    (0.05256061628460884, -0.2538454532623291),
    (-0.3308587670326233, -0.26200100779533386),
    (-0.05224471166729927, 0.2748788893222809),
    (-0.11462058871984482, -0.09864940494298935),
    (0.20291109383106232, 0.15218333899974823),
]


def test_collisions_at_hypot_rounding_cases() -> None:
    """64 fields, so that torch's hypot would take its vectorised loop; the first few overlap."""
    pos = torch.zeros(64, 2, 2)
    pos[:, 1] = 5.0
    pos[: len(HYPOT_CASES), 1] = torch.tensor(HYPOT_CASES)
    numba_out, torch_out = both(resolve_collisions, pos, torch.ones_like(pos), torch.tensor([0.3, 0.3]), 10)
    assert_same_bits(numba_out, torch_out)
    assert numba_out[2][: len(HYPOT_CASES)].all() and not numba_out[2][len(HYPOT_CASES) :].any()


def test_collisions_check_the_radii() -> None:
    with pytest.raises(ValueError, match=r"radius has shape \(3,\); expected \(2,\), one per object"):
        resolve_collisions(torch.zeros(1, 2, 2), torch.zeros(1, 2, 2), torch.ones(3))


def test_coincident_objects_separate_alike() -> None:
    pos = torch.zeros(3, 4, 2)
    pos[1, 2] = pos[1, 1] = torch.tensor([1.0, -1.0])
    radius = torch.tensor([0.085, 0.3, 0.3, 0.3])
    numba_out, torch_out = both(resolve_collisions, pos, torch.ones_like(pos), radius, 10)
    assert_same_bits(numba_out, torch_out)
    assert numba_out[2].all()


SERVER = TASKS["server"]
EXACT = TASKS["exact"]


@pytest.mark.parametrize(
    ("preset", "keepers", "takers", "noise", "options"),
    [
        ("2005", 3, 2, True, EXACT),
        ("rcss19", 4, 3, True, EXACT),
        ("2005", 5, 4, False, EXACT),
        ("rcss19", 3, 2, True, SERVER),  # every player's own world model: the kernels run per view
        ("2005", 4, 3, True, SERVER),
    ],
)
def test_simulated_episodes_identical(
    one_thread: None, preset: str, keepers: int, takers: int, noise: bool, options: dict
) -> None:
    sims = [
        KeepawaySimulator(
            48,
            KeepawayConfig(
                preset=preset,
                keepers=keepers,
                takers=takers,
                movement_noise=noise,
                kernels=kernels,
                **options,
            ),
            seed=3,
        )
        for kernels in ("numba", "torch")
    ]
    assert [sim.kernels for sim in sims] == ["numba", "torch"]
    ended = 0
    for _ in range(100):  # about 10 s of play a field: most start an episode anew
        for sim in sims:
            obs, _ = sim.observe(sim.decision().holder)
            outcome = sim.step(hand_coded_actions(obs, keepers, takers), auto_reset=True)
        ended += int(outcome.ended.sum())
        for name, value in sims[0].state.tensors().items():
            assert torch.equal(bits(value), bits(getattr(sims[1].state, name))), name
    assert ended > 0


def test_kernel_choice() -> None:
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert resolve_kernels("auto", cpu) == "numba"
    assert resolve_kernels("auto", cpu, torch.float64) == "torch"
    assert resolve_kernels("auto", cuda) == "torch"
    assert resolve_kernels("torch", cpu) == "torch"
    with pytest.raises(ValueError, match="kernels='numba' runs float32 on the CPU only"):
        resolve_kernels("numba", cuda)
    with pytest.raises(ValueError, match=r"kernels='fast' is invalid; allowed: auto, numba, torch"):
        KeepawayConfig(kernels="fast")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_gpu_torch_path_follows_cpu() -> None:
    """The GPU runs the torch path; from one state, its cycles agree with the CPU's to rounding
    (transcendental functions differ in the last bit), and a seed fixes its episodes."""
    for options in (EXACT, SERVER):
        config = KeepawayConfig(movement_noise=False, **options)
        cpu = KeepawaySimulator(256, config, seed=5)
        gpus = [KeepawaySimulator(256, config, device="cuda", seed=5) for _ in range(2)]
        for gpu in gpus:
            gpu.state = dataclasses.replace(
                cpu.state, **{k: v.cuda() for k, v in cpu.state.tensors().items()}
            )
        for _ in range(5):
            for sim in (cpu, *gpus):
                obs, _ = sim.observe(sim.decision().holder)
                sim.step(hand_coded_actions(obs, 3, 2))
        torch.testing.assert_close(gpus[0].state.pos.cpu(), cpu.state.pos, atol=1e-3, rtol=0)
        for name, value in gpus[0].state.tensors().items():
            assert torch.equal(value, getattr(gpus[1].state, name)), name
