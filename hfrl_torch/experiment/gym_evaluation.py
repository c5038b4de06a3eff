"""``evaluate.py`` on ``domain=gym``: play N fresh episodes of a saved policy (DQN's Q or PPO's logits, fused
with the saved H^ by the run's rule and last weight, or TAMER's H^ alone), a reference callable, or random
actions, and report the mean return with a 95 % interval."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential

from hfrl_torch import keys
from hfrl_torch.agents.policies import load_policy
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.imports import load_callable
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.gym_task import GymTask
from hfrl_torch.experiment.checks import gym_spaces, plays_on_domain_task
from hfrl_torch.experiment.command_line import task_overrides
from hfrl_torch.experiment.factories import make_gym_task, set_threads
from hfrl_torch.experiment.learners.gym_dqn import gym_env, play_returns
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight
from hfrl_torch.trainers.reference_oracle import Reference, right_actions

__all__ = ["evaluate_gym", "format_gym_summary"]


class _Chooser(TensorDictModuleBase):
    """A policy module writing ``keys.ACTION`` from a function of the observation batch."""

    def __init__(self, choose: Any) -> None:
        super().__init__()
        self.choose = choose
        self.in_keys, self.out_keys = [keys.OBSERVATION], [keys.ACTION]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        return tensordict.set(keys.ACTION, self.choose(tensordict.get(keys.OBSERVATION)))


def _reference_policy(reference: Reference, actions: int) -> TensorDictSequential:
    def choose(obs: torch.Tensor) -> torch.Tensor:
        return right_actions(reference, obs, actions).to(torch.int64).argmax(-1)  # the first right action

    return TensorDictSequential(_Chooser(choose))


def _random_policy(actions: int, seed: int) -> TensorDictSequential:
    generator = torch.Generator().manual_seed(seed)

    def choose(obs: torch.Tensor) -> torch.Tensor:
        return torch.randint(actions, (obs.shape[0],), generator=generator)

    return TensorDictSequential(_Chooser(choose))


def _policy(cfg: DictConfig) -> tuple[str, GymTask, TensorDictSequential, Fusion, str]:
    """(label, task, policy, fusion, what plays) of ``policy``: a gym run or checkpoint (on its own
    task), a reference ``module:callable`` or ``random`` (on ``domain``'s task)."""
    name = "random" if cfg.policy is None else str(cfg.policy)
    idle = Fusion("none", "none", ConstantWeight(0.0)).eval()
    if plays_on_domain_task(name):
        task, spaces = make_gym_task(cfg), gym_spaces(cfg)
        if name == "random":
            policy = _random_policy(spaces.actions, int(cfg.seed) + 1)
            return name, task, policy, idle, "uniformly random actions"
        reference = load_callable(name, "policy")
        try:
            right_actions(reference, spaces.sample.clone(), spaces.actions)  # its shape, checked once
        except ValueError as exc:
            raise ConfigError(f"policy={name!r} {exc}") from None
        return name, task, _reference_policy(reference, spaces.actions), idle, "the reference policy"
    if not Path(name).exists():
        raise ConfigError(
            f"policy={name!r} is invalid for domain=gym; allowed: a gym run directory or checkpoint, random, "
            "or a reference policy package.module:callable"
        )
    explicit = [o for o in task_overrides() if o.startswith("domain.") and not o.startswith("domain.batch=")]
    if explicit:
        raise ConfigError(
            f"{explicit[0]} does not apply to a checkpoint, which is played on the task it learned "
            "(set only domain.batch, episodes and seed)"
        )
    ckpt = load_checkpoint(name, domain="gym")
    policy, info = load_policy(ckpt)
    task = make_gym_task(OmegaConf.create({"domain": info["task"]}))
    return str(ckpt["path"]), task, policy, info["fusion"], info["describe"]


def evaluate_gym(cfg: DictConfig) -> dict[str, object]:
    """Play ``episodes`` fresh episodes of ``policy`` (``domain.batch`` at a time, seeds from ``seed``) and
    return the JSON summary: mean return with a 95 % interval."""
    set_threads(cfg)
    label, task, policy, fusion, plays = _policy(cfg)
    episodes, batch, seed = int(cfg.episodes), int(cfg.domain.batch), int(cfg.seed)
    returns: list[torch.Tensor] = []
    t0 = time.perf_counter()
    for start in range(0, episodes, batch):
        n = min(batch, episodes - start)
        env = gym_env(task, n, seed + start)
        try:
            returns.append(play_returns(env, policy, fusion))
        finally:
            env.close()
    elapsed = time.perf_counter() - t0
    s = summarize(torch.cat(returns))
    return {
        "domain": "gym",
        "task": task.label,
        "policy": label,
        "plays": plays,
        "episodes": episodes,
        **{k: s[k] for k in ("mean", "sd", "median", "ci95_low", "ci95_high", "min", "max")},
        "episodes_per_s": episodes / max(elapsed, 1e-9),
        "seed": seed,
    }


def format_gym_summary(r: dict[str, object]) -> str:
    """Human-readable lines above the final JSON line."""
    return "\n".join(
        [
            f"{r['task']}: {r['policy']} ({r['plays']})",
            f"  {r['episodes']} episodes: mean return {r['mean']:.2f}, 95% CI {r['ci95_low']:.2f}.."
            f"{r['ci95_high']:.2f}, median {r['median']:.2f}, sd {r['sd']:.2f} (min {r['min']:.1f}, max "
            f"{r['max']:.1f})",
        ]
    )
