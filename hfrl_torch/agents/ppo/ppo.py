"""PPO (Schulman et al. 2017, "Proximal Policy Optimization Algorithms") assembled from TorchRL's parts,
with a trainer's H^ fused into the policy's preferences through the one fusion component.

Read top to bottom as CleanRL's ``ppo.py``: a ``ProbabilisticActor`` samples actions from a ``Categorical``
over the policy network's logits, a ``ValueOperator`` is the critic, ``torchrl.objectives.value.GAE`` turns a
collected batch ``[B, T]`` into advantages and value targets once, and ``torchrl.objectives.ClipPPOLoss``
(clipped ratio, entropy bonus, critic loss, advantages normalised per minibatch) is minimised by Adam for
``epochs`` passes over shuffled minibatches, the gradient's norm clipped.

Fusion. The logits are written as ``keys.ENV_VALUES`` (R, the policy's preference of every action, as PG's
logits on Tetris) and, with a trainer, a :class:`~hfrl_torch.fusion.transform.FusionModule` of the run's
:class:`~hfrl_torch.fusion.fusion.Fusion` turns them and H^ into ``keys.FUSED_VALUES``, the logits the
``Categorical`` samples from: ``linear``, ``annealed`` and ``action_biasing`` give
``softmax(logits + w H^)`` (the thesis's eq. 4.2 and Knox & Stone's action biasing, with R the policy's
preference), ``control_sharing`` H^'s own softmax with probability min(w, 1) and the policy's otherwise,
``none`` the policy alone (H^ still learned, its match rate counted). The fused policy is the one PPO
optimises: H^ and w enter as inputs, not parameters, and the loss reads them as they were when the action
was chosen (``keys.HUMAN_VALUES`` and :data:`PLAYED_WEIGHT`, stored by the collector), so the ratio
pi_new / pi_old measures only the policy network's change and starts at 1 (``keys.FUSION_WEIGHT`` for the
additive rules; for control sharing 1 where the coin followed H^, 0 where not, which the fusion's
evaluation mode turns back into the same choice without a new draw). A row that followed H^ has a ratio of
1 whatever the network does: it teaches the critic, not the actor. With ``fusion.normalise=spread`` the
loss scales H^ by the logits' running spread as it stands at the update, not as it stood at each
decision. Reward-level rules (``reward_shaping``) reach PPO as the reward GAE reads (the env's
``FeedbackFusion``), not here.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from tensordict.utils import NestedKey
from torch import nn
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss
from torchrl.objectives.value import GAE

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.transform import FusionModule

__all__ = ["PLAYED_WEIGHT", "PPO", "PlayedWeight"]

PLAYED_WEIGHT = "fusion_weight_played"  # [B] the weight the loss re-fuses each stored decision with
_LOSS_WEIGHT = "fusion_weight_loss"  # where the loss's FusionModule writes its weight (not kept)


class PlayedWeight(TensorDictModuleBase):
    """Writes :data:`PLAYED_WEIGHT`: the weight of each decision as the loss must replay it (the module
    docstring): the fused weight, or for control sharing whether the coin followed H^ (1.0) or not (0.0)."""

    def __init__(self, fusion: Fusion) -> None:
        super().__init__()
        self.control_sharing = fusion.decision == "control_sharing"
        self.in_keys = [keys.FUSED_VALUES, keys.HUMAN_VALUES, keys.FUSION_WEIGHT]
        self.out_keys = [PLAYED_WEIGHT]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        weight = tensordict.get(keys.FUSION_WEIGHT)
        if self.control_sharing:  # the rows that followed H^ hold H^ itself as their fused values
            fused, human = tensordict.get(keys.FUSED_VALUES), tensordict.get(keys.HUMAN_VALUES)
            weight = (fused == human.to(fused.dtype)).all(-1).to(weight.dtype)
        tensordict.set(PLAYED_WEIGHT, weight)
        return tensordict


class PPO:
    """PPO-Clip on one policy network and one critic (see the module docstring).

    :param actor: the policy network, observation ``[*, S]`` to one logit per action ``[*, A]``.
    :param critic: the value network, observation to ``[*, 1]``.
    :param in_key: the observation both read.
    :param fusion: the run's fusion component (None: the policy alone, no H^ in the tensordict).
    :param lr: Adam's step size (actor and critic together, as CleanRL).
    :param gamma: the discount per step.
    :param lmbda: GAE's lambda.
    :param clip_epsilon: the ratio's clip range, 1 +- this.
    :param entropy_coeff: the entropy bonus's weight.
    :param critic_coeff: the critic loss's weight.
    :param epochs: passes over each collected batch.
    :param minibatch_size: transitions per gradient step.
    :param max_grad_norm: the gradient's norm is clipped to this.
    :param seed: seeds the minibatches' shuffling.
    """

    def __init__(
        self,
        actor: nn.Module,
        critic: nn.Module,
        in_key: NestedKey = keys.OBSERVATION,
        fusion: Fusion | None = None,
        *,
        lr: float = 1e-3,
        gamma: float = 0.99,
        lmbda: float = 0.95,
        clip_epsilon: float = 0.2,
        entropy_coeff: float = 0.01,
        critic_coeff: float = 0.5,
        epochs: int = 4,
        minibatch_size: int = 128,
        max_grad_norm: float = 0.5,
        seed: int = 0,
    ) -> None:
        self.actor_net, self.critic_net, self.fusion = actor, critic, fusion
        self.epochs, self.minibatch_size, self.max_grad_norm = int(epochs), int(minibatch_size), max_grad_norm
        logits = TensorDictModule(actor, in_keys=[in_key], out_keys=[keys.ENV_VALUES])
        if fusion is None:
            self.actor = self._actor(logits, keys.ENV_VALUES)
            replay = self.actor
        else:  # collection fuses with the schedule's weight; the loss replays each decision's own
            self.actor = self._actor(
                TensorDictSequential(logits, FusionModule(fusion), PlayedWeight(fusion)), keys.FUSED_VALUES
            )
            replay = self._actor(
                TensorDictSequential(
                    logits,
                    FusionModule(
                        fusion, count=False, weight_key=PLAYED_WEIGHT, fusion_weight_key=_LOSS_WEIGHT
                    ),
                ),
                keys.FUSED_VALUES,
            )
        self.critic = ValueOperator(critic, in_keys=[in_key])
        self.advantage = GAE(gamma=gamma, lmbda=lmbda, value_network=self.critic, average_gae=False)
        self.loss = ClipPPOLoss(
            replay,
            self.critic,
            clip_epsilon=clip_epsilon,
            entropy_coeff=entropy_coeff,
            critic_coeff=critic_coeff,
            normalize_advantage=True,
        )
        self.optimizer = torch.optim.Adam(self.loss.parameters(), lr=lr)
        self.generator = torch.Generator().manual_seed(int(seed))
        self.updates = 0

    @staticmethod
    def _actor(module: TensorDictModuleBase, logits_key: NestedKey) -> ProbabilisticActor:
        return ProbabilisticActor(
            module,
            in_keys={"logits": logits_key},
            distribution_class=torch.distributions.Categorical,
            return_log_prob=True,
        )

    def update(self, batch: TensorDictBase) -> dict[str, float]:
        """Learn from one collected batch ``[B, T]`` (time last); returns the mean losses of its steps."""
        with torch.no_grad():
            self.advantage(batch)
        data = batch.reshape(-1)
        totals: dict[str, float] = {"loss": 0.0, "loss_objective": 0.0, "loss_critic": 0.0, "entropy": 0.0}
        steps = 0
        evaluating = self.fusion is not None and self.fusion.evaluating
        if self.fusion is not None:
            self.fusion.eval(True)  # replay the stored decisions: no draws, no match count
        try:
            for _ in range(self.epochs):
                order = torch.randperm(data.shape[0], generator=self.generator)
                for start in range(0, data.shape[0], self.minibatch_size):
                    out = self.loss(data[order[start : start + self.minibatch_size]])
                    loss = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                    self.optimizer.zero_grad()
                    loss.backward()
                    nn.utils.clip_grad_norm_(self.loss.parameters(), self.max_grad_norm)
                    self.optimizer.step()
                    steps += 1
                    totals["loss"] += float(loss.detach())
                    for k in ("loss_objective", "loss_critic", "entropy"):
                        totals[k] += float(out[k].detach())
        finally:
            if self.fusion is not None:
                self.fusion.eval(evaluating)
        self.updates += steps
        return {k: v / max(steps, 1) for k, v in totals.items()}

    def state_dict(self) -> dict[str, Any]:
        """Both networks, Adam's moments, the shuffling generator and the update count."""
        return {
            "actor": self.actor_net.state_dict(),
            "critic": self.critic_net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`'s output; a malformed one raises ``CheckpointError``."""
        try:
            self.actor_net.load_state_dict(state["actor"])
            self.critic_net.load_state_dict(state["critic"])
            self.optimizer.load_state_dict(state["optimizer"])
            self.generator.set_state(state["generator"])
            self.updates = int(state["updates"])
        except (KeyError, TypeError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"bad PPO state in the checkpoint ({e!r})") from None
