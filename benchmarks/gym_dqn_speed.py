"""Frames per second of DQN on CartPole-v1: this project's learner against the same DQN written on TorchRL.

    python benchmarks/gym_dqn_speed.py [--repeats 3] [--set agent.frames=12000 ...]

Prints one JSON object (progress on stderr). Two sides, alternating in this one process (project, TorchRL,
project, TorchRL, ...), after one uncounted warm-up run of each:

- ``project``: the learner of ``train.py domain=gym domain.env_id=CartPole-v1 agent=dqn fusion=none
  trainer=none logger.backend=none threads=1``, built as ``train.py`` builds it (the checked config,
  ``set_threads``, ``learner_for(...)(cfg, run_dir)``) and run by ``experiment.run.learn``: its collector,
  ``DQNLoss``, replay buffer, the greedy evaluation at every point, ``metrics.jsonl`` and the checkpoints;
- ``torchrl``: the same DQN as a plain script on TorchRL's parts, no project code: the same batched env
  (gymnasium's ``SyncVectorEnv`` with same-step autoreset behind ``GymWrapper``, index actions) with
  ``RewardSum``, ``QValueActor`` over the same MLP, ``EGreedyModule``, ``Collector``, ``DQNLoss`` with
  ``SoftUpdate``, ``TensorDictReplayBuffer`` on a ``LazyTensorStorage``, Adam, and the same evaluation.

Every hyperparameter is read from the project's composed config (conf/agent/dqn.yaml's ``by_domain.gym``
and conf/domain/gym.yaml), so both sides run the same numbers; the defaults are: ``agent.frames`` 12000 env
steps of all boards together; ``agent.boards`` 8 CartPole-v1 copies (its own 500-step limit);
``agent.steps_per_batch`` 4 (32 frames per collector batch); ``agent.learn_after`` 1000 frames before the
first update; ``agent.frames_per_update`` 8 (4 gradient steps per batch); ``agent.batch_size`` 64;
``agent.buffer_size`` 20000; Adam ``agent.lr`` 0.001; ``agent.gamma`` 0.99 (TD(0) target); ``agent.tau``
0.01 (``SoftUpdate(eps=0.99)`` after each gradient step); ``agent.double`` true (double DQN, delayed
target); epsilon-greedy from ``agent.epsilon_start`` 0.3 to ``agent.epsilon_end`` 0.02 over
``agent.epsilon_frames`` 6000 frames; Q an MLP of ``agent.cells`` [64, 64] ReLU from the 4 observations
(scaled by one over each finite bound: x by 1/4.8, theta by 1/0.419) to 2 action values; a greedy evaluation
of ``agent.eval_episodes`` 10 fresh episodes (one per board of a 10-board env, the same seed each time) at
frame 0 and every ``agent.eval_every`` 3000 frames (5 in all). ``--set key=value`` changes any of them for
both sides (the test's tiny budget).

Reported per run: set-up seconds (project: config check and learner; TorchRL: envs, modules, collector), the
run's wall seconds and process CPU seconds, frames per second of each (frames / run seconds), and the
greedy returns at each point (both must learn: the returns differ, as the two draw different random
numbers). The ratio is project / TorchRL of the median frames per second, wall and CPU, and the median of
each round's own ratio. One torch thread on both sides: the project keeps torch at one intra-op thread
(``set_threads``; its ops are small), and on this 2-core machine shared with other work a second thread
would only contend; the TorchRL side is set the same so that the two compare.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import logging
import os
import platform
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gymnasium as gym
import numba
import torch

torch.set_num_threads(1)
numba.set_num_threads(1)

from omegaconf import DictConfig, OmegaConf  # noqa: E402
from tensordict.nn import TensorDictSequential  # noqa: E402
from torch import nn  # noqa: E402
from torchrl.collectors import Collector  # noqa: E402
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer  # noqa: E402
from torchrl.envs import EnvBase, GymWrapper, RewardSum, TransformedEnv  # noqa: E402
from torchrl.modules import MLP, EGreedyModule, QValueActor  # noqa: E402
from torchrl.objectives import DQNLoss, SoftUpdate  # noqa: E402

from hfrl_torch.experiment.cli import compose_train  # noqa: E402
from hfrl_torch.experiment.factories import set_threads  # noqa: E402
from hfrl_torch.experiment.registry import learner_for  # noqa: E402
from hfrl_torch.experiment.run import Interrupt, RunFiles, learn  # noqa: E402

logging.getLogger("torchrl").setLevel(logging.WARNING)  # its INFO lines go to stdout, which is the JSON

TASK = ("domain=gym", "domain.env_id=CartPole-v1", "agent=dqn", "fusion=none", "trainer=none")
COMMON = ("logger.backend=none", "threads=1", "seed=0")
TARGET = 0.67  # the issue's: the project at >= 0.67x plain TorchRL's frames per second
EVAL_SEED = 12345  # the TorchRL side's evaluation episodes (the same at every point)


def project_config(sets: list[str]) -> DictConfig:
    """The checked config of the project's run (``train.py``'s, with ``sets`` on top)."""
    return compose_train(*TASK, *COMMON, *sets)


# ------------------------------------------------------------------------------------ the project's side


class Stopwatch:
    """Wall and process CPU seconds spent inside the calls it wraps (the greedy evaluations)."""

    def __init__(self) -> None:
        self.wall = self.cpu = 0.0

    def wrap(self, fn: Callable[..., Any]) -> Callable[..., Any]:
        """``fn``, timed."""

        def timed(*args: Any) -> Any:
            w, c = time.perf_counter(), time.process_time()
            try:
                return fn(*args)
            finally:
                self.wall += time.perf_counter() - w
                self.cpu += time.process_time() - c

        return timed


def run_project(cfg: DictConfig, run_dir: Path) -> dict[str, Any]:
    """One ``train.py`` run of ``cfg``'s learner, timed: set-up, then the loop (points and checkpoints)."""
    run_dir.mkdir(parents=True)  # Hydra makes it for train.py
    t0 = time.perf_counter()
    set_threads(cfg)
    learner = learner_for(str(cfg.agent.name), str(cfg.domain.name))(cfg, run_dir, None)
    evaluations = Stopwatch()
    learner.greedy_evaluation = evaluations.wrap(learner.greedy_evaluation)
    built, c0 = time.perf_counter(), time.process_time()
    learn(learner, RunFiles(run_dir, cfg), interrupt=Interrupt())
    wall, cpu = time.perf_counter() - built, time.process_time() - c0
    returns = [round(float(r["eval/greedy_return_mean"]), 2) for r in learner.history if "frames" in r]
    return timing(learner.frames, built - t0, wall, cpu, evaluations, returns, learner.dqn.updates)


# ------------------------------------------------------------------------------------ plain TorchRL's side


class Scaled(nn.Module):
    """An MLP whose inputs are first multiplied by a fixed vector (CartPole's x and theta by one over their
    bounds), as the project's Q network does."""

    def __init__(self, scale: torch.Tensor, net: nn.Module) -> None:
        super().__init__()
        self.register_buffer("scale", scale)
        self.net = net

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return self.net(observation * self.scale)


def cartpole_batch(boards: int, seed: int) -> EnvBase:
    """``boards`` CartPole-v1 in one synchronous vector env behind ``GymWrapper``, with each episode's
    return."""
    vector = gym.vector.SyncVectorEnv(
        [lambda: gym.make("CartPole-v1")] * boards, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP
    )
    env = TransformedEnv(GymWrapper(vector, categorical_action_encoding=True), RewardSum())
    env.set_seed(seed)
    return env


@torch.no_grad()
def greedy_returns(env: EnvBase, actor: nn.Module) -> float:
    """The mean return of one greedy episode on every board of ``env``, the same episodes each call."""
    env.set_seed(EVAL_SEED)
    td = env.reset()
    b = td.batch_size[0]
    returns = torch.zeros(b)
    finished = torch.zeros(b, dtype=torch.bool)
    while not bool(finished.all()):
        td, root = env.step_and_maybe_reset(actor(td))
        done = td["next", "done"].reshape(-1) & ~finished
        returns = torch.where(done, td["next", "episode_reward"].reshape(-1), returns)
        finished |= done
        td = root
    return float(returns.mean())


def run_torchrl(cfg: DictConfig) -> dict[str, Any]:
    """The same DQN (``cfg.agent``'s numbers) as a plain TorchRL script, timed like the project's run."""
    a = cfg.agent
    t0 = time.perf_counter()
    torch.manual_seed(int(cfg.seed))
    env = cartpole_batch(int(a.boards), int(cfg.seed))
    eval_env = cartpole_batch(int(a.eval_episodes), EVAL_SEED)
    space = gym.make("CartPole-v1").observation_space
    bound = torch.maximum(torch.as_tensor(space.low).abs(), torch.as_tensor(space.high).abs())
    scale = torch.where(torch.isfinite(bound) & (bound > 0), 1.0 / bound, 1.0).to(torch.float32)
    net = MLP(in_features=4, out_features=2, num_cells=list(a.cells), activation_class=nn.ReLU)
    actor = QValueActor(Scaled(scale, net), in_keys=["observation"], spec=env.action_spec_unbatched)
    explore = EGreedyModule(
        env.action_spec,
        eps_init=float(a.epsilon_start),
        eps_end=float(a.epsilon_end),
        annealing_num_steps=int(a.epsilon_frames),
    )
    policy = TensorDictSequential(actor, explore)
    loss = DQNLoss(actor, action_space=env.action_spec_unbatched, delay_value=True, double_dqn=bool(a.double))
    loss.make_value_estimator(gamma=float(a.gamma))
    target = SoftUpdate(loss, eps=1.0 - float(a.tau))
    optimizer = torch.optim.Adam(loss.parameters(), lr=float(a.lr))
    buffer = TensorDictReplayBuffer(
        storage=LazyTensorStorage(int(a.buffer_size)), batch_size=int(a.batch_size)
    )
    frames_per_batch = int(a.boards) * int(a.steps_per_batch)
    collector = Collector(env, policy, frames_per_batch=frames_per_batch, total_frames=int(a.frames))
    updates_per_batch = max(1, round(frames_per_batch / float(a.frames_per_update)))
    evaluations = Stopwatch()
    evaluate = evaluations.wrap(greedy_returns)
    built, c0 = time.perf_counter(), time.process_time()
    frames, updates, next_eval = 0, 0, 0
    returns = [round(evaluate(eval_env, actor), 2)]
    next_eval += int(a.eval_every)
    for batch in collector:
        buffer.extend(batch.reshape(-1))
        frames += batch.numel()
        explore.step(batch.numel())
        if len(buffer) >= int(a.learn_after):
            for _ in range(updates_per_batch):
                value = loss(buffer.sample())["loss"]
                optimizer.zero_grad()
                value.backward()
                optimizer.step()
                target.step()
                updates += 1
        if frames >= min(next_eval, int(a.frames)):
            returns.append(round(evaluate(eval_env, actor), 2))
            next_eval += int(a.eval_every)
    wall, cpu = time.perf_counter() - built, time.process_time() - c0
    collector.shutdown()
    env.close()
    eval_env.close()
    return timing(frames, built - t0, wall, cpu, evaluations, returns, updates)


# ----------------------------------------------------------------------------------------------- report


def timing(
    frames: int,
    setup: float,
    wall: float,
    cpu: float,
    evaluations: Stopwatch,
    returns: list[float],
    updates: int,
) -> dict[str, Any]:
    """One run's record: frames per second over the whole run and over its training alone (the greedy
    evaluations left out: their length follows how well each side's policy happens to balance the pole)."""
    return {
        "frames": frames,
        "updates": updates,
        "setup_s": round(setup, 3),
        "wall_s": round(wall, 3),
        "cpu_s": round(cpu, 3),
        "eval_wall_s": round(evaluations.wall, 3),
        "eval_cpu_s": round(evaluations.cpu, 3),
        "frames_per_s": round(frames / wall, 1),
        "frames_per_cpu_s": round(frames / cpu, 1),
        "train_frames_per_s": round(frames / (wall - evaluations.wall), 1),
        "train_frames_per_cpu_s": round(frames / (cpu - evaluations.cpu), 1),
        "greedy_returns": returns,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3, help="counted runs of each side")
    parser.add_argument("--set", nargs="*", default=[], help="config overrides for both sides (key=value)")
    parser.add_argument("--no-warmup", action="store_true", help="count every run (no uncounted first pair)")
    parser.add_argument(
        "--profile",
        type=Path,
        help="then one run of each side under cProfile: <stem>_project.prof, _torchrl.prof",
    )
    args = parser.parse_args()
    cfg = project_config(list(args.set))
    a = cfg.agent
    warm = int(a.learn_after) + 8 * int(a.boards) * int(a.steps_per_batch)
    warm_cfg = project_config([*args.set, f"agent.frames={warm}", f"agent.eval_every={warm}"])
    runs: dict[str, list[dict[str, Any]]] = {"project": [], "torchrl": []}
    load_before = [round(x, 2) for x in os.getloadavg()]
    with tempfile.TemporaryDirectory() as tmp:
        rounds = [("warmup", warm_cfg)] * (not args.no_warmup) + [("counted", cfg)] * args.repeats
        for r, (kind, c) in enumerate(rounds):
            for side, run in (
                ("project", lambda c=c, r=r: run_project(c, Path(tmp) / f"project-{r}")),
                ("torchrl", lambda c=c: run_torchrl(c)),
            ):
                result = run()
                record = {"round": r, "kind": kind, "side": side, **result}
                print(json.dumps(record), file=sys.stderr, flush=True)
                if kind == "counted":
                    runs[side].append(result)
        if args.profile is not None:  # after the counted runs: cProfile slows what it watches
            for side, run in (
                ("project", lambda: run_project(cfg, Path(tmp) / "project-profiled")),
                ("torchrl", lambda: run_torchrl(cfg)),
            ):
                profile = cProfile.Profile()
                profile.runcall(run)
                profile.dump_stats(str(args.profile.with_name(f"{args.profile.stem}_{side}.prof")))
    load_after = [round(x, 2) for x in os.getloadavg()]

    measures = ("frames_per_s", "frames_per_cpu_s", "train_frames_per_s", "train_frames_per_cpu_s")
    medians = {side: {m: statistics.median(run[m] for run in runs[side]) for m in measures} for side in runs}
    ratios = {}
    for m in measures:
        pairs = zip(runs["project"], runs["torchrl"], strict=True)
        ratios[m] = {
            "of_medians": round(medians["project"][m] / medians["torchrl"][m], 3),
            "per_round": round(statistics.median(p[m] / t[m] for p, t in pairs), 3),
        }
    settings = OmegaConf.to_container(a, resolve=True)
    print(
        json.dumps(
            {
                "benchmark": "gym_dqn_speed",
                "task": "CartPole-v1",
                "settings": {k: v for k, v in settings.items() if k != "by_domain"},
                "repeats": args.repeats,
                "medians": medians,
                "ratios": ratios,  # project / TorchRL
                "target": TARGET,
                "meets_target": {m: r["of_medians"] >= TARGET for m, r in ratios.items()},
                "runs": runs,
                "threads": {"torch": torch.get_num_threads(), "numba": numba.get_num_threads()},
                "cores": os.cpu_count(),
                "load_before": load_before,
                "load_after": load_after,
                "machine": f"{platform.machine()} {platform.processor() or platform.platform()}",
                "torch": torch.__version__,
            },
            default=str,
        )
    )


if __name__ == "__main__":
    main()
