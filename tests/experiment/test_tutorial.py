"""docs/tutorial.md, "Your own task in an afternoon": its task (examples/catch.py) passes TorchRL's spec
checks through the gym domain's wrapper, renders frames the browser can show, and the tutorial's train.py and
evaluate.py commands, at a tiny budget, learn a policy that beats random actions."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import gymnasium as gym
import numpy as np
import torch
from omegaconf import OmegaConf
from script_runner import run_script
from torchrl.envs import check_env_specs

from examples.catch import BALLS, HEIGHT, Catch, make, reference
from hfrl_torch.envs.gym_task import GymTask, first_frame, make_gym_batch, task_spaces
from hfrl_torch.experiment.aggregate import find_runs, group_runs, report
from hfrl_torch.experiment.cli import compose_train
from hfrl_torch.experiment.train import _compare_lines, _config_dir_args

ROOT = Path(__file__).resolve().parents[2]
TASK = ("domain=gym", "domain.make=examples.catch:make", "domain.seconds_per_step=0.5")
TINY = (
    "agent.frames=768",
    "agent.eval_every=384",
    "agent.boards=4",
    "agent.learn_after=128",
    "agent.epsilon_frames=400",
    "agent.eval_episodes=4",
    "fusion.weight=1.0",
    "human.lr=0.005",
    "human.replay_every=2",
    "trainer.frequency=1.0",
    "trainer.timing.enabled=false",
    "threads=1",
)


def run(script: str, *args: str) -> subprocess.CompletedProcess:
    """``python <script> <args>`` from the repository root, as the tutorial types it."""
    out = run_script(script, *args, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out


def summary(out: subprocess.CompletedProcess) -> dict:
    """evaluate.py's last line: its JSON summary."""
    return json.loads(out.stdout.strip().splitlines()[-1])


def random_return(episodes: int) -> float:
    """The mean return of uniformly random actions over ``episodes`` seeded episodes of Catch."""
    env, total = Catch(), 0.0
    env.action_space.seed(0)
    for episode in range(episodes):
        env.reset(seed=episode)
        ended = False
        while not ended:
            _, reward, ended, _, _ = env.step(int(env.action_space.sample()))
            total += reward
    return total / episodes


def test_catch_passes_the_spec_checks_and_renders_rgb_frames(one_thread) -> None:
    env = make_gym_batch(GymTask(make=make), 3, seed=0)
    check_env_specs(env)
    spaces = task_spaces(GymTask(make=make))
    assert (spaces.observation_size, spaces.actions) == (3, 3)
    frame = first_frame(GymTask(make=make).make_watched())
    assert frame.shape[2] == 3 and frame.dtype == np.uint8 and frame.max() > frame.min()


def test_the_reference_catches_every_ball_and_an_episode_is_ten_balls() -> None:
    env = Catch()
    obs, _ = env.reset(seed=7)
    total, steps, ended = 0.0, 0, False
    while not ended:
        obs, reward, ended, truncated, _ = env.step(int(reference(torch.as_tensor(obs)[None])[0]))
        total, steps = total + reward, steps + 1
        assert not truncated
    assert total == BALLS and steps == BALLS * (HEIGHT - 1)
    assert isinstance(env.action_space, gym.spaces.Discrete) and env.action_space.n == 3


def test_the_tutorials_train_and_evaluate_commands_learn_to_beat_random(tmp_path) -> None:
    run_dir = tmp_path / "dqn_linear"
    teach = ("agent=dqn", "fusion=linear", "trainer=oracle", "trainer.reference=examples.catch:reference")
    out = run("train.py", *TASK, *teach, *TINY, f"hydra.run.dir={run_dir}")
    assert "Compare:" in out.stderr and (run_dir / "checkpoints" / "last.pt").is_file()
    played = summary(run("evaluate.py", "domain=gym", f"policy={run_dir}", "episodes=20"))  # its own task
    assert played["task"] == "examples.catch:make" and played["episodes"] == 20
    random = random_return(20)
    assert played["mean"] >= random + 2.0, (played["mean"], random)  # random: about 2 of 10
    last = json.loads((run_dir / "metrics.jsonl").read_text().splitlines()[-1])["eval/greedy_return_mean"]
    rows, _ = report(group_runs(find_runs([run_dir])[0]))  # evaluate.py runs=<dir> reads the gym curve
    assert rows[0]["metric"] == "eval/greedy_return_mean" and rows[0]["mean"] == last


def test_a_named_domains_compare_line_keeps_the_users_config_dir(tmp_path) -> None:
    """A run of ``--config-dir myconf domain=catch`` prints a ``Compare:`` sweep that finds its domain."""
    sources = OmegaConf.create(
        [
            {"path": "hydra.conf", "schema": "pkg", "provider": "hydra"},
            {"path": str(ROOT / "conf"), "schema": "file", "provider": "main"},
            {"path": str(tmp_path), "schema": "file", "provider": "command-line"},
        ]
    )
    own = _config_dir_args(sources)
    assert own == ["--config-dir", str(tmp_path)]
    job = [*TASK, "agent=dqn", "fusion=linear", "trainer.reference=examples.catch:reference"]
    compare = _compare_lines(compose_train(*job), "python", [*own, *job])[0]
    assert compare.startswith(f"Compare:          python train.py -m --config-dir {tmp_path} domain=gym ")
