"""Train a TorchRL learner on the fused reward: a collector over ``TransformedEnv(env, FeedbackFusion(...))``.

A simulated trainer (Griffith et al.'s oracle: a program, not a person) judges every placement on a batched
``TetrisEnv``; ``HumanFeedback`` writes its events into each step's ``next`` and ``FeedbackFusion`` turns the
step's reward into ``r + w h`` (reward shaping; the env's own reward stays under ``env_reward``). The policy
is an ordinary ``TensorDictModule``, the data come from TorchRL's ``Collector``, and the learner (linear
Q-learning over afterstate features, one per board) trains on ``("next", "reward")``, the fused reward::

    python examples/torchrl_collector.py --frames 40000 --weight 0.5
    python examples/torchrl_collector.py --frames 40000 --weight 0      # the environment's reward alone
"""

from __future__ import annotations

import argparse
import json

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.envs import Compose, TransformedEnv

from hfrl_torch import keys
from hfrl_torch.agents.qlearning import LinearQLearning
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.fusion import FeedbackFusion
from hfrl_torch.trainers import OracleTrainer
from hfrl_torch.trainers.transform import HumanFeedback


class EpsilonGreedy(nn.Module):
    """The policy: epsilon-greedy placements over a linear Q of their afterstates."""

    def __init__(self, q: LinearQLearning, epsilon: float) -> None:
        super().__init__()
        self.q, self.epsilon = q, epsilon

    def forward(self, features: torch.Tensor, mask: torch.Tensor, terminal: torch.Tensor) -> torch.Tensor:
        return self.q.act(features, mask, terminal, self.epsilon)


def make_env(boards: int, weight: float, seed: int) -> TransformedEnv:
    """Tetris boards whose reward is fused with a simulated trainer's feedback."""
    trainer = OracleTrainer(frequency=0.5, consistency=0.9, seed=seed)
    env = TetrisEnv(batch=boards, rules=TetrisRules(8, 8), max_pieces=400, seed=seed)
    fusion = FeedbackFusion("reward_shaping", weight, estimate_key=None, feedback_key=keys.FEEDBACK)
    return TransformedEnv(env, Compose(HumanFeedback(trainer), fusion))


def learn_from(q: LinearQLearning, batch: TensorDictBase) -> None:
    """Q-learning steps over a collected batch ``[B, T]``, in time order, on the fused reward."""
    for t in range(batch.shape[1]):
        step = batch[:, t]
        nxt = step["next"]
        feats = step[keys.AFTERSTATE_FEATURES]
        chosen = feats[torch.arange(feats.shape[0]), step[keys.ACTION]]
        q.td_update(
            chosen,
            nxt[keys.REWARD].reshape(-1),
            nxt[keys.AFTERSTATE_FEATURES],
            nxt[keys.ACTION_MASK],
            nxt[keys.AFTERSTATE_TERMINAL],
            nxt[keys.TERMINATED].reshape(-1),
        )


def train(frames: int, weight: float, boards: int = 8, steps: int = 50, seed: int = 0) -> dict[str, float]:
    """Collect ``frames`` placements; returns the lines per game of the games that ended, and the feedback."""
    env = make_env(boards, weight, seed)
    q = LinearQLearning(env.base_env.num_features, boards, alpha=0.002, gamma=0.9, seed=seed)
    policy = TensorDictModule(
        EpsilonGreedy(q, 0.05),
        in_keys=[keys.AFTERSTATE_FEATURES, keys.ACTION_MASK, keys.AFTERSTATE_TERMINAL],
        out_keys=[keys.ACTION],
    )
    collector = Collector(
        env,
        policy,
        frames_per_batch=boards * steps,
        total_frames=frames,
        auto_register_policy_transforms=False,
    )
    lines, given, shaped = [], 0, 0.0
    for batch in collector:
        learn_from(q, batch)
        nxt = batch["next"]
        done = nxt[keys.DONE].reshape(-1)
        lines += nxt[keys.LINES].reshape(-1)[done].tolist()
        given += int(nxt[keys.FEEDBACK_MASK].sum())
        shaped += float((nxt[keys.REWARD] - nxt[keys.ENV_REWARD]).sum())
    collector.shutdown()
    return {
        "frames": frames,
        "weight": weight,
        "games": len(lines),
        "lines_per_game": sum(lines) / max(len(lines), 1),
        "feedback_events": given,
        "shaping_total": shaped,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, default=40_000)
    parser.add_argument("--weight", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(json.dumps(train(args.frames, args.weight, seed=args.seed)))


if __name__ == "__main__":
    main()
