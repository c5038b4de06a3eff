"""Frames per second of the DQN's data path: TorchRL's collector against the project's own loop, in one run.

    python benchmarks/collector_speed.py [--seconds 3] [--boards 1 8 64 256]

Prints one JSON object. Tetris 10x10 (the ``domain=tetris`` default), one thread, the untrained DQN's Q
network (``agent=dqn``: an MLP over every placement's BT afterstate features) choosing every placement; only
collection is timed (no gradient step). For each batch size B (boards played at once) four paths:

- ``own_loop``: the project's own loop, no TensorDict: the numba engine's ``afterstates()``, Q on the
  features, masked argmax, ``step()``, resetting ended boards (the loop of the linear learners);
- ``env_step``: the learner's ``TransformedEnv(TetrisEnv, Compose(FeedbackFusion))`` stepped by hand with
  ``step_and_maybe_reset`` and its TensorDict policy (Q module, greedy, TorchRL's ``EGreedyModule``);
- ``collector``: the same env and policy through TorchRL's ``Collector`` (``agent.steps_per_batch`` steps of
  every board per batch), as ``train.py agent=dqn`` collects;
- ``collector_trainer``: the collector of ``agent=dqn fusion=linear trainer=oracle human=mlp``: the simulated
  oracle's feedback transform, Deep TAMER's H^ and the fused choice on the path too.

A frame is one placement of one board. The ratio ``collector / own_loop`` is TorchRL's cost on the data path.
"""

from __future__ import annotations

import argparse
import json
import platform
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numba
import torch

torch.set_num_threads(1)
numba.set_num_threads(1)

from tensordict import TensorDictBase  # noqa: E402

from hfrl_torch.envs.tetris.engine_numba import NumbaEngine  # noqa: E402
from hfrl_torch.envs.tetris.features import BT  # noqa: E402
from hfrl_torch.experiment.cli import compose_train  # noqa: E402
from hfrl_torch.experiment.learners.tetris_dqn import TetrisDQN  # noqa: E402

TAUGHT = (
    "fusion=linear",
    "fusion.weight=trust",
    "trainer=oracle",
    "human=mlp",
)  # the weight measured in docs


def make_learner(boards: int, run_dir: Path, *overrides: str) -> TetrisDQN:
    """The ``agent=dqn`` Tetris learner of ``train.py`` with ``boards`` boards (its collector built)."""
    cfg = compose_train("agent=dqn", f"agent.boards={boards}", "logger.backend=none", *overrides)
    return TetrisDQN(cfg, run_dir)


def timed(step: Callable[[], int], seconds: float) -> float:
    """Frames per second of calling ``step`` (which returns its frames) for ``seconds``, after a warm-up."""
    for _ in range(3):
        step()
    frames, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds or frames == 0:
        frames += step()
    return frames / (time.perf_counter() - t0)


@torch.no_grad()
def bench_own_loop(learner: TetrisDQN, boards: int, seconds: float) -> float:
    """The numba engine and the learner's Q network, no TensorDict, no TorchRL env."""
    q = learner.dqn.model
    engine = NumbaEngine(learner.env.base_env.rules, boards, BT)
    gen = torch.Generator().manual_seed(0)
    engine.reset(torch.ones(boards, dtype=torch.bool), torch.randint(0, 2**62, (boards,), generator=gen))

    def step() -> int:
        feats, mask, _, _ = engine.afterstates()
        alive = int(torch.as_tensor(engine.alive).sum())
        values = q(feats).masked_fill(~mask, float("-inf"))
        engine.step(values.argmax(-1))
        dead = ~torch.as_tensor(engine.alive)
        if bool(dead.any()):
            engine.reset(dead, torch.randint(0, 2**62, (boards,), generator=gen))
        return alive

    return timed(step, seconds)


@torch.no_grad()
def bench_env_step(learner: TetrisDQN, boards: int, seconds: float) -> float:
    """The learner's transformed env and TensorDict policy, stepped by hand."""
    env, policy = learner.env, learner.policy
    state: dict[str, TensorDictBase] = {"td": env.reset()}

    def step() -> int:
        _, state["td"] = env.step_and_maybe_reset(policy(state["td"]))
        return boards

    return timed(step, seconds)


def bench_collector(learner: TetrisDQN, seconds: float) -> float:
    """TorchRL's collector of the learner (``next`` on its iterator: one batch [B, steps_per_batch])."""
    return timed(lambda: next(learner.batches).numel(), seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="timed seconds per path and batch size")
    parser.add_argument("--boards", type=int, nargs="+", default=[1, 8, 64, 256])
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for boards in args.boards:
            # one learner per path: a collector keeps its env's state between batches, so no other path
            # may step that env
            by_hand = make_learner(boards, Path(tmp) / f"hand{boards}")
            plain = make_learner(boards, Path(tmp) / f"plain{boards}")
            taught = make_learner(boards, Path(tmp) / f"taught{boards}", *TAUGHT)
            row = {
                "boards": boards,
                "own_loop_fps": bench_own_loop(by_hand, boards, args.seconds),
                "env_step_fps": bench_env_step(by_hand, boards, args.seconds),
                "collector_fps": bench_collector(plain, args.seconds),
                "collector_trainer_fps": bench_collector(taught, args.seconds),
            }
            row["collector_over_own_loop"] = row["collector_fps"] / row["own_loop_fps"]
            # the extra time of one step of all B boards: flat in B where it is per-call overhead
            row["collector_extra_ms_per_step"] = (
                1e3 * boards * (1.0 / row["collector_fps"] - 1.0 / row["own_loop_fps"])
            )
            rows.append(row)
            for learner in (by_hand, plain, taught):
                learner.collector.shutdown()
    print(
        json.dumps(
            {
                "benchmark": "collector_speed",
                "domain": "tetris 10x10, agent=dqn, untrained Q over BT afterstates, collection only",
                "frame": "one placement of one board",
                "steps_per_batch": 4,
                "threads": 1,
                "torch": torch.__version__,
                "machine": platform.machine(),
                "rows": rows,
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
