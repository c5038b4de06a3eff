"""PPO on any Gymnasium task (or a TorchRL env of the user's), alone or with a trainer's H^ fused:
``train.py domain=gym domain.env_id=<id> agent=ppo [fusion=<scheme> trainer=oracle trainer.reference=...]``.

The policy and the critic are MLPs on the observation vector (inputs scaled as DQN's, ``gym_dqn``), trained
by :class:`~hfrl_torch.agents.ppo.PPO` (TorchRL's ``ClipPPOLoss`` and ``GAE``) on the batches TorchRL's
``Collector`` draws from ``agent.boards`` copies of the task, wrapped as
``TransformedEnv(env, Compose(StepCounter, RewardSum, <trainer's feedback>, FeedbackFusion(fusion)))``.
With a trainer, H^ is Deep TAMER's MLP on the observation (``human=mlp``), taught by the simulated oracle
against ``trainer.reference`` (or the value proxy, a replayed log, or a person in the browser watching
board 0: ``trainer=interactive``, ``gym_page``); every step of a batch, in time order, H^ records the
decision and learns from the feedback delivered, and each ended episode ends the fusion's episode (the trust
factor of eq. 4.4, the adaptive bandit) with its return above ``domain.min_return``; then PPO learns from
the batch.

How H^ meets PPO. The project's feedback spec (``shared/specs/feedback.md``, "Combining H^ with the
environment") fuses R, "the environment-trained estimate", with H^ at the choice, a = argmax_a f(R, H), and
offers Knox & Stone's techniques, of which "action biasing and control sharing were the most robust when H
and the environment are learned at the same time". A policy's estimate of each action is its logit, so:

- **decision level** (``linear``, ``annealed``, ``action_biasing``, ``control_sharing``, ``none``): the
  fusion acts on the policy's preferences, its logits, as it acts on DQN's Q: the action is sampled from
  ``softmax(logits + w H^)`` (control sharing: from H^'s softmax with probability min(w, 1)), and that
  fused policy is the one PPO optimises (``agents.ppo``'s docstring says how its ratio stays the network's
  own). H^'s feedback units and the logits' nats need no rescaling: w H^ = 1 multiplies an action's odds
  by e. The greedy policy (the curve's points, ``evaluate.py``) is argmax of the fused logits.
- **reward level** (``reward_shaping``): PPO learns from r + w H^(s, a), GAE's reward, the policy alone
  choosing.
- **refused**: ``exponential`` scales R by a factor of H^ and assumes R >= 0, but a logit has no sign of its
  own (a softmax ignores a shift of every logit); ``human_only`` acts on H^ alone, which on-policy PPO
  cannot learn from (its policy never acts): ``agent=dqn fusion=human_only`` is Deep TAMER alone. And
  ``fusion.normalise=true`` would rescale the logits to [0, 1] per decision, capping how sure the softmax
  can ever be.

The points are the greedy policy's mean return on ``agent.eval_episodes`` fresh episodes, the same seeds at
every point. Checkpoints hold both networks, Adam's moments, the shuffling generator, H^ (with Deep TAMER's
feedback buffer), the fusion, the transforms' state and the random state; the episodes in progress restart
on a resume (the collector's batch is not saved), as DQN's do.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from hfrl_torch import keys
from hfrl_torch.agents.dqn import ChosenEstimate, HumanValuesModule
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.agents.ppo import PPO
from hfrl_torch.common.logger import Logger
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.experiment.checks import check_gym_ppo
from hfrl_torch.experiment.factories import (
    make_deep_tamer,
    make_fusion,
    make_gym_trainer,
)
from hfrl_torch.experiment.learners.deep_q import CollectorLearner
from hfrl_torch.experiment.learners.gym_dqn import GymTaskParts, greedy_returns, observation_net
from hfrl_torch.experiment.learners.gym_page import SCORE_KEY, GymPage
from hfrl_torch.experiment.run import Point, WallClockSaves
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.transform import FeedbackFusion
from hfrl_torch.trainers.transform import HumanFeedback

__all__ = ["GymPPO"]


def _observation(td: TensorDictBase) -> torch.Tensor:
    return td.get(keys.OBSERVATION)


class GymPPO(GymTaskParts, GymPage, CollectorLearner):
    """PPO over the observation of any discrete-action task on ``agent.boards`` copies (module docstring)."""

    domain = "gym"
    agent = "ppo"
    score_key = SCORE_KEY
    score_unit = "return per episode"
    default_scaling = "none"  # logits + w H^ raw: H^ = 1 at w = 1 multiplies an action's odds by e

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_gym_ppo(cfg)

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        super().__init__(cfg, run_dir, checkpoint)
        a = cfg.agent
        self.seed = int(cfg.seed)
        torch.manual_seed(component_seed(self.seed, "agent"))  # network initialisation, the actions' samples
        self.boards, self.steps_per_batch = int(a.boards), int(a.steps_per_batch)
        self.frames_total, self.eval_every = int(a.frames), int(a.eval_every)
        self.taught = cfg.trainer.name != "none"
        self.fusion: Fusion = make_fusion(cfg, type(self), 1)
        cells = list(a.cells)
        actor = observation_net(self.spaces, cells, self.scale)
        critic = observation_net(self.spaces, cells, self.scale, outputs=1)
        self.ppo = PPO(
            actor,
            critic,
            keys.OBSERVATION,
            self.fusion if self.taught else None,
            lr=float(a.lr),
            gamma=float(a.gamma),
            lmbda=float(a.lmbda),
            clip_epsilon=float(a.clip_epsilon),
            entropy_coeff=float(a.entropy_coeff),
            critic_coeff=float(a.critic_coeff),
            epochs=int(a.epochs),
            minibatch_size=int(a.minibatch_size),
            max_grad_norm=float(a.max_grad_norm),
            seed=component_seed(self.seed, "replay"),  # the minibatches' shuffling
        )
        self.human = self.log = self.feedback_transform = None
        modules: list[TensorDictModuleBase] = [self.ppo.actor]
        if self.taught:
            model = observation_net(self.spaces, list(cfg.human.cells), self.scale)
            self.human = make_deep_tamer(cfg, model, _observation, self.boards)
            wiring = self.page_wiring(run_dir, lambda log: make_gym_trainer(cfg, self.spaces.actions, log))
            self.log, self.teaching = wiring.log, wiring.teaching
            departure = wiring.departure
            self.feedback_transform = HumanFeedback(
                wiring.trainer, self.seconds_per_step, score_key=keys.EPISODE_REWARD, departure=departure
            )
            modules = [HumanValuesModule(self.human, [keys.OBSERVATION]), self.ppo.actor, ChosenEstimate()]
        self.policy = TensorDictSequential(*modules)
        self.reward_fusion = FeedbackFusion(self.fusion, estimate_key=keys.HUMAN_REWARD_ESTIMATE)
        parts = [*self.page_transforms(), *filter(None, [self.feedback_transform]), self.reward_fusion]
        self.env = TransformedEnv(
            self.page_env(self.boards, component_seed(self.seed, "env")), Compose(*parts), auto_unwrap=True
        )
        self.frames = self.points = self.episodes = self.events = self.positive = 0
        self.trainer_seconds = 0.0
        self.losses: list[dict[str, float]] = []
        self.finished: list[float] = []  # returns of the training episodes ended since the last point
        self.weights_played: list[float] = []
        if checkpoint is not None:
            self._load(checkpoint["state"])
        fusion, rng = copy.deepcopy(self.fusion.state_dict()), torch.get_rng_state()
        self.collector = Collector(
            self.env,
            self.policy,
            frames_per_batch=self.boards * self.steps_per_batch,
            total_frames=-1,
            auto_register_policy_transforms=False,
        )
        self.fusion.load_state_dict(fusion)  # the collector's probe of the policy's outputs is no decision:
        torch.set_rng_state(rng)  # it neither counts in the trust's match rate nor draws the actions' samples
        self.batches = iter(self.collector)
        self.saves = WallClockSaves()

    # ---------------------------------------------------------------- the loop

    @property
    def description(self) -> str:
        return "PPO gym" + (f" + {self.cfg.fusion.name}" if self.taught else "")

    def start(self, logger: Logger) -> None:
        if self.taught and not self.resumed:
            logger.text("trainer", f"{self.who}; fusion={self.cfg.fusion.name}, human={self.cfg.human.name}")
        self.announce_page()

    def advance(self) -> list[Point]:
        if self.points == 0 and not self.resumed and self.frames == 0:
            points = [self._point()]  # the untrained policy: where every curve starts
        else:
            goal = min(self.frames_total, self.points * self.eval_every)
            while self.frames < goal and not self.ending:
                self._learn_batch(next(self.batches))
            # ended early (Finish and save, Ctrl-C): the checkpoint keeps the frames, a resumed run goes on
            points = [self._point()] if self.frames >= goal else []
        self.show_points(points)
        return points

    def _learn_batch(self, batch: TensorDictBase) -> None:
        """One collected batch [B, T]: H^ and the fusion's episodes in time order, then PPO's epochs."""
        for t in range(batch.shape[1]):
            step = batch[:, t]
            nxt = step["next"]
            if self.taught:
                self.human.record(step, step[keys.ACTION], step[keys.CLOCK])
                self.events += int(self.human.learn(nxt).sum())
                self.positive += int((nxt[keys.FEEDBACK_MASK] & (nxt[keys.FEEDBACK] > 0)).sum())
                if self.feedback_transform.present_at(self.episodes, step[keys.CLOCK]):
                    self.trainer_seconds += self.watched_boards * self.seconds_per_step
            done = nxt[keys.DONE].reshape(-1)
            for ret in nxt[keys.EPISODE_REWARD].reshape(-1)[done].tolist():
                if self.taught:
                    self.weights_played.append(float(self.fusion.weight()[0]))
                    above = max(0.0, ret - float(self.cfg.domain.min_return))
                    self.fusion.end_episode(torch.ones(1, dtype=torch.bool), above)
                self.finished.append(float(ret))
                self.episodes += 1
        self.losses.append(self.ppo.update(batch))
        self.frames += batch.numel()

    def greedy_evaluation(self) -> dict[str, float]:
        """The greedy policy (argmax of the fused logits, the fusion in evaluation mode) on the same fresh
        episodes at every point."""
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            return greedy_returns(self.task, self.eval_episodes, self.seed, self.policy, self.fusion)

    def agent_record(self) -> dict[str, float]:
        losses = {
            f"train/{k}": sum(x[k] for x in self.losses) / len(self.losses) if self.losses else math.nan
            for k in ("loss", "loss_objective", "loss_critic", "entropy")
        }
        return {**losses, "train/updates": self.ppo.updates}

    # ------------------------------------------------------------- checkpoints

    def checkpoint(self) -> dict[str, Any]:
        return {
            "state": {**self.common_state(), "ppo": self.ppo.state_dict(), **self.page_state()},
            "policy": self.policy_payload(),
        }

    def _load(self, state: dict[str, Any]) -> None:
        self.ppo.load_state_dict(state["ppo"])
        self.load_common_state(state)
        self.load_page_state(state)

    def policy_payload(self) -> dict[str, Any]:
        """What ``evaluate.py`` plays: the policy network greedily (and, with a trainer, fused with H^ by the
        run's rule at its last weight)."""
        human = None
        if self.taught:
            cells = list(self.cfg.human.cells)
            human = {"kind": "mlp", "cells": cells, "model": self.human.model.state_dict()}
        return export_policy(
            "gym_ppo",
            task=OmegaConf.to_container(self.cfg.domain, resolve=True),
            observation_size=self.spaces.observation_size,
            observation_shape=list(self.spaces.observation_shape),
            actions=self.spaces.actions,
            scale=list(self.scale),
            cells=list(self.cfg.agent.cells),
            actor=self.ppo.actor_net.state_dict(),
            fusion=self.fusion_payload(),
            human=human,
        )

    def close(self) -> None:
        self.collector.shutdown()
        self.end_teaching("agent.frames", 2 * self.frames_total)
        if self.log is not None:
            self.log.close()
