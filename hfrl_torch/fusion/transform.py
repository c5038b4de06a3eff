"""The TorchRL faces of the fusion component: ``FeedbackFusion`` on the env, ``FusionModule`` in the policy.

:class:`FeedbackFusion` is a transform that trains the learner on a fused reward: Knox & Stone's reward
shaping ``R' = R + beta H^`` (AAMAS 2010), the thesis's linear (eq. 4.2) and exponential (eq. 5.1) rules
applied to the reward, or either signal alone. The environment's own reward is kept, unchanged, under
``env_reward`` for evaluation and logging. :class:`FusionModule` is the decision face: in a policy it reads
R and H^ of every action and writes the fused values (and, with ``select="greedy"``, the action). Both hand
the arithmetic to one :class:`~hfrl_torch.fusion.fusion.Fusion`, which may be shared with the training
loop that updates its weights.

Where ``FeedbackFusion`` reads H:

- ``estimate_key`` (default ``"human_reward_estimate"``): ``H^(s, a)`` of the action taken, ``[*B, 1]``,
  written by the policy into the tensordict next to the action, before ``env.step``. The transform
  declares it in the state spec (an input, like the action) and in the observation spec, with the default
  0: a reset writes 0, and every step writes 0 into ``next`` so that a policy which does not write a fresh
  estimate fuses with 0 and never with the previous step's (the ``TensorDictPrimer`` pattern, with the
  primer's value reset at every step). An absent estimate reads as 0.
- ``feedback_key`` (e.g. ``keys.FEEDBACK``): the person's reward for this step, ``[*B, 1]`` or the
  channel's ``[*B, K]`` slots (summed), 0 where none was given, written into ``next`` by the env or by an
  earlier transform of a ``Compose`` (``trainers.transform.HumanFeedback``). It must be there when asked for.
- both: the person's own reward where they gave one (nonzero), H^ elsewhere.

Several agents in one env (keepaway's keepers, an SMDP): with ``agent_key`` the estimate written with an
action belongs to the agent named there, and a step's reward belongs to the agent that decides next (its
reward since its own last decision), so it is fused with *that* agent's last estimate; at an episode's end
``agent_rewards_key`` ``[*B, n]`` (every agent's last reward) is fused agent by agent. Rewards of boards where
nobody decides (``deciding_key`` false) and nothing ends are left alone.

Weights: with a shared :class:`~hfrl_torch.fusion.fusion.Fusion` they are its current ones (board b is
learner b, or all boards learner 0), the loop that shares it ending its episodes. Otherwise they come from
the transform's own :class:`~hfrl_torch.fusion.schedules.WeightSchedule` evaluated at each board's episode
index, episodes being delimited by done flags: a board's index advances by one after the step
whose done flag is set (that step is fused with its own episode's weight), once per episode even if the
board is stepped again before its reset; a reset clears the flag for the boards it restarts and touches no
other board.

Learned weights. A weight learned from whole episodes alone (``BanditWeight``: each episode's return of R)
is learned here: the transform that owns its schedule ends the schedule's episode at each board's done flag
(``Fusion.end_episode`` with the episode's return of the env reward and whether H was nonzero in it), so the
weight learns with reward-level fusion alone, in any TorchRL loop. A weight that learns from what a reward
transform never sees is refused at construction with a one-line error: the trust factor (eq. 4.4) needs the
match rate of decisions, argmax R against argmax H^ over every action, which only
:class:`FusionModule` counts; the paired and searched weights need the learner's own test games or search.
Give those a :class:`Fusion` shared with the policy's ``FusionModule`` and with the loop that ends its
episodes, or ``end_episodes=True`` to have this transform end them on done flags (performance: the
episode's return of R).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.data import Categorical, Composite, OneHot, TensorSpec, Unbounded
from torchrl.envs.transforms import Transform

from hfrl_torch import keys
from hfrl_torch.common.resets import reset_flags
from hfrl_torch.fusion.fusion import Fusion, choosable
from hfrl_torch.fusion.schedules import WeightSchedule, as_schedule
from hfrl_torch.fusion.schemes import REWARD_SCHEMES
from hfrl_torch.models.linear import greedy_placement

__all__ = ["ACTION_SPACES", "HUMAN_REWARD_ESTIMATE", "FeedbackFusion", "FusionModule", "action_space_of"]

HUMAN_REWARD_ESTIMATE = keys.HUMAN_REWARD_ESTIMATE
# the weights learned from evidence a reward transform never sees (refused without a shared Fusion)
UNSEEN_EVIDENCE = {
    "trust": "the match rate of decisions (argmax R against argmax H^, counted by FusionModule)",
    "paired": "test games the learner plays at several weights",
    "search": "the learner's own search",
}


def _float_dtype(dtype: torch.dtype) -> torch.dtype:
    return dtype if dtype.is_floating_point else torch.get_default_dtype()


class FeedbackFusion(Transform):
    """Fuse the env reward R with the person's reward H into the reward the learner sees.

    ``reward <- f(R, H)`` with ``f`` one of :data:`~hfrl_torch.fusion.schemes.REWARD_SCHEMES` (see
    :func:`~hfrl_torch.fusion.schemes.fuse_values`), ``env_reward <- R``. The module docstring says where H is
    read and how episodes are counted.

    :param scheme: ``none``, ``human_only``, ``linear``, ``exponential`` or ``reward_shaping``; or a
        :class:`Fusion` (its reward rule and weights, shared with whoever updates them).
    :param weight: ``w`` / ``beta``: a number, one number per board, or a :class:`WeightSchedule` (per board:
        learners along the env's first batch dimension); ignored with a ``Fusion``.
    :param estimate_key: where the policy writes ``H^(s, a)`` (None: not used).
    :param feedback_key: where the person's reward for the step arrives in ``next`` (None: not used).
    :param reward_key: the env reward, replaced by the fused one.
    :param env_reward_key: where the env reward is kept.
    :param done_key: the done flag that ends an episode.
    :param reset_key: the partial-reset flag.
    :param agent_key: the root entry naming the agent that acts (several agents per board; None: one).
    :param agents: n, the agents per board (with ``agent_key``).
    :param deciding_key: the entry saying which boards' agent decides (with ``agent_key``; None: all).
    :param agent_rewards_key: every agent's reward at an episode's end, ``[*B, n]`` (with ``agent_key``).
    :param end_episodes: end the schedule's episodes on done flags (the module docstring); None: when the
        transform owns a weight learned from episodes (``BanditWeight``), not with a shared ``Fusion``.

    Offline (``transform(rollout)``), the transform re-fuses a stored trajectory ``[*B, T]`` (time last, as
    ``env.rollout`` and collectors lay it out): R from ``("next", env_reward)`` if present, else
    ``("next", reward)``; episodes counted from 0 by the done flags along time (each done is taken to have
    been followed by a reset). With a constant or annealed weight it reproduces the online fused rewards of a
    rollout that started at episode 0; a trust schedule gives its current trust everywhere.

    Example:
        >>> env = TransformedEnv(TetrisEnv(batch=4), FeedbackFusion("reward_shaping", AnnealedWeight(2.0)))
        >>> td = env.reset()
        >>> td["action"], td["human_reward_estimate"] = policy(td)  # H^ of the chosen placement
        >>> out = env.step(td)["next"]  # out["reward"]: R + beta H^, out["env_reward"]: R
    """

    def __init__(
        self,
        scheme: str | Fusion = "linear",
        weight: float | Sequence[float] | Tensor | WeightSchedule = 1.0,
        *,
        estimate_key: NestedKey | None = HUMAN_REWARD_ESTIMATE,
        feedback_key: NestedKey | None = None,
        reward_key: NestedKey = keys.REWARD,
        env_reward_key: NestedKey = keys.ENV_REWARD,
        done_key: NestedKey = keys.DONE,
        reset_key: NestedKey = keys.RESET,
        agent_key: NestedKey | None = None,
        agents: int = 1,
        deciding_key: NestedKey | None = None,
        agent_rewards_key: NestedKey | None = None,
        end_episodes: bool | None = None,
    ) -> None:
        if isinstance(scheme, Fusion):
            fusion = scheme
        elif scheme not in REWARD_SCHEMES:
            hint = (
                "; action_biasing and control_sharing act at selection: use FusionModule"
                if scheme in ("action_biasing", "control_sharing")
                else ""
            )
            raise ValueError(
                f"FeedbackFusion scheme={scheme!r} is invalid; allowed: {', '.join(REWARD_SCHEMES)}{hint}"
            )
        else:
            fusion = Fusion("none", scheme, as_schedule(weight))
        self._shared = isinstance(scheme, Fusion)  # its weights are the loop's; else counted here
        kind = fusion.schedule.kind
        if not self._shared and kind in UNSEEN_EVIDENCE:
            raise ValueError(
                f"FeedbackFusion weight={fusion.schedule!r} learns from {UNSEEN_EVIDENCE[kind]}, which a "
                "reward transform never sees; pass a Fusion shared with the FusionModule and loop that give "
                "it, or a number, AnnealedWeight or BanditWeight"
            )
        learned = kind not in ("constant", "annealed")
        self.end_episodes = (not self._shared and learned) if end_episodes is None else bool(end_episodes)
        if estimate_key is None and feedback_key is None:
            raise ValueError("FeedbackFusion needs estimate_key, feedback_key or both: where to read H from")
        if agent_key is not None and (agents < 1 or estimate_key is None):
            raise ValueError("FeedbackFusion with agent_key needs agents >= 1 and an estimate_key")
        in_keys = [reward_key, *(k for k in (estimate_key, feedback_key) if k is not None)]
        out_keys = [reward_key, env_reward_key, *([agent_rewards_key] if agent_rewards_key else [])]
        super().__init__(in_keys=in_keys, out_keys=out_keys)
        self.fusion = fusion
        self.scheme = fusion.reward_rule
        self.agent_key, self.agents = agent_key, int(agents)
        self.deciding_key, self.agent_rewards_key = deciding_key, agent_rewards_key
        self._pending: Tensor | None = None  # [*B, n] each agent's last estimate (several agents)
        self._last_agent: Tensor | None = None  # [*B] the agent that decided last
        self.estimate_key = estimate_key
        self.feedback_key = feedback_key
        self.reward_key = reward_key
        self.env_reward_key = env_reward_key
        self.done_key = done_key
        self.reset_key = reset_key
        self._episodes: Tensor | None = None
        self._finished: Tensor | None = None
        self._returns: Tensor | None = None  # each board's return of R in its episode (with end_episodes)
        self._taught: Tensor | None = None  # each board's episode had a nonzero H

    @property
    def schedule(self) -> WeightSchedule:
        """The weights' schedule (the fusion's)."""
        return self.fusion.schedule

    @property
    def episodes(self) -> Tensor | None:
        """Each board's episode index (int64, the env's batch shape), or None before the first reset."""
        return self._episodes

    def _counters(self, batch: torch.Size, device: torch.device | None) -> Tensor:
        if self._episodes is None or self._episodes.shape != batch:
            if self._episodes is not None:
                raise ValueError(
                    f"FeedbackFusion counts episodes of batch {tuple(self._episodes.shape)}, got a "
                    f"tensordict of batch {tuple(batch)}"
                )
            boards, learners = batch.numel(), self.fusion.learners
            if self.end_episodes and learners not in (1, boards):
                raise ValueError(
                    f"FeedbackFusion ends episodes of {learners} learners on {boards} boards; allowed: one "
                    "learner, or one per board"
                )
            self._episodes = torch.zeros(batch, dtype=torch.int64, device=device)
            self._finished = torch.zeros(batch, dtype=torch.bool, device=device)
        return self._episodes

    def _human(self, root: TensorDictBase, nxt: TensorDictBase, reward: Tensor) -> Tensor:
        estimate = feedback = None
        if self.estimate_key is not None:
            estimate = root.get(self.estimate_key, None)
        if self.feedback_key is not None:
            feedback = nxt.get(self.feedback_key, None)
            if feedback is None:
                raise KeyError(
                    f"FeedbackFusion reads the person's reward from ('next', {self.feedback_key!r}), "
                    "which is absent; put the transform that writes it (0 where no feedback) before this one"
                )
        estimate = self._like(estimate, reward, self.estimate_key)
        feedback = self._like(feedback, reward, self.feedback_key)
        if feedback is None:
            return estimate if estimate is not None else torch.zeros_like(reward)
        if estimate is None:
            return feedback
        return torch.where(feedback != 0, feedback, estimate)

    @staticmethod
    def _like(value: Tensor | None, reward: Tensor, key: NestedKey | None) -> Tensor | None:
        if value is None:
            return None
        if value.ndim == reward.ndim and value.shape[:-1] == reward.shape[:-1] and value.shape[-1] > 1:
            value = value.sum(-1, keepdim=True)  # the channel's K slots of one step (0 where empty)
        if value.shape != reward.shape:
            if value.numel() != reward.numel():
                raise ValueError(
                    f"{key!r} has shape {tuple(value.shape)}; expected one per reward, {tuple(reward.shape)}"
                )
            value = value.reshape(reward.shape)
        return value.to(device=reward.device)

    def _done(self, nxt: TensorDictBase) -> Tensor:
        done = nxt.get(self.done_key, None)
        if done is None:
            raise KeyError(
                f"FeedbackFusion counts episodes from ('next', {self.done_key!r}), which is absent"
            )
        batch = nxt.batch_size
        return done.reshape(*batch, -1).any(-1) if done.ndim > len(batch) else done.reshape(batch)

    def _fuse(self, reward: Tensor, human: Tensor, episodes: Tensor) -> Tensor:
        if self.scheme == "none":
            return reward
        if self._shared:  # the loop that shares the fusion ends its episodes: its current weights
            rows = episodes.reshape(-1).shape[0] if episodes.ndim else 1
            learners = self.fusion.learners
            w = self.fusion.weight(
                torch.arange(rows) % learners if learners > 1 else torch.zeros(rows, dtype=torch.int64)
            )
            w = w.reshape(episodes.shape)
        else:
            w = self.fusion.weight(episodes=episodes)
        fused = self.fusion.reward(reward, human, w)
        return fused.to(_float_dtype(reward.dtype))

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        reward = next_tensordict.get(self.reward_key)
        human = self._human(tensordict, next_tensordict, reward) if self.agent_key is None else None
        episodes = self._counters(next_tensordict.batch_size, reward.device)
        done = self._done(next_tensordict).to(episodes.device)
        if human is not None:
            fused = self._fuse(reward, human, episodes)
        else:
            fused = self._fuse_agents(tensordict, next_tensordict, reward, episodes, done)
        next_tensordict.set(self.reward_key, fused)
        next_tensordict.set(self.env_reward_key, reward)
        if self.estimate_key is not None:
            next_tensordict.set(self.estimate_key, torch.zeros_like(reward, dtype=_float_dtype(reward.dtype)))
        ended = done & ~self._finished
        if self.end_episodes:
            self._end_episodes(reward, human, ended)
        self._episodes = episodes + ended.to(torch.int64)
        self._finished = self._finished | done
        return next_tensordict

    def _end_episodes(self, reward: Tensor, human: Tensor | None, ended: Tensor) -> None:
        """Add this step to each board's return and end the schedule's episode of every board that ended."""
        boards = ended.numel()
        if self._returns is None or self._returns.numel() != boards:
            self._returns = torch.zeros(boards, dtype=torch.float64)
            self._taught = torch.zeros(boards, dtype=torch.bool)
        self._returns += reward.detach().reshape(boards, -1).sum(-1).cpu().to(torch.float64)
        if human is not None:
            self._taught |= (human.detach().reshape(boards, -1) != 0).any(-1).cpu()
        flags = ended.reshape(boards).cpu()
        if not bool(flags.any()):
            return
        learners = self.fusion.learners
        if learners == boards:
            self.fusion.end_episode(flags, self._returns.clone(), self._taught if human is not None else None)
        else:  # one learner (checked with the counters): each board's episode is one of its, in board order
            for b in flags.nonzero().flatten().tolist():
                taught = self._taught[b : b + 1] if human is not None else None
                self.fusion.end_episode(torch.ones(1, dtype=torch.bool), self._returns[b : b + 1], taught)
        self._returns = torch.where(flags, 0.0, self._returns)
        self._taught = self._taught & ~flags

    def _fuse_agents(
        self, root: TensorDictBase, nxt: TensorDictBase, reward: Tensor, episodes: Tensor, done: Tensor
    ) -> Tensor:
        """Several agents per board: each reward is fused with the last estimate of the agent it is due to."""
        batch = nxt.batch_size
        pending, last = self._agent_state(batch, reward.device)
        estimate = self._like(root.get(self.estimate_key, None), reward, self.estimate_key)
        acted = self._deciding(root, batch)
        agent = root.get(self.agent_key).reshape(batch).to(torch.int64)
        if estimate is not None:
            at = torch.nn.functional.one_hot(agent, self.agents).to(torch.bool) & acted.unsqueeze(-1)
            pending = torch.where(at, estimate.reshape(*batch, 1).to(pending.dtype), pending)
        last = torch.where(acted, agent, last)
        due_agent = torch.where(done, last, nxt.get(self.agent_key).reshape(batch).to(torch.int64))
        due = done | self._deciding(nxt, batch)
        human = pending.gather(-1, due_agent.unsqueeze(-1)).reshape(reward.shape)
        fused = torch.where(due.reshape(*batch, 1), self._fuse(reward, human, episodes), reward)
        if self.agent_rewards_key is not None and bool(done.any()):
            ends = nxt.get(self.agent_rewards_key)
            fused_ends = self._fuse(ends, pending.to(ends.device), episodes).to(ends.dtype)
            nxt.set(self.agent_rewards_key, torch.where(done.unsqueeze(-1), fused_ends, ends))
        self._pending = torch.where(done.unsqueeze(-1), 0.0, pending)
        self._last_agent = last
        return fused.to(_float_dtype(reward.dtype))

    def _deciding(self, td: TensorDictBase, batch: torch.Size) -> Tensor:
        if self.deciding_key is None:
            return torch.ones(batch, dtype=torch.bool, device=td.device)
        return td.get(self.deciding_key).reshape(batch).to(torch.bool)

    def _agent_state(self, batch: torch.Size, device: torch.device | None) -> tuple[Tensor, Tensor]:
        if self._pending is None or self._pending.shape[:-1] != batch:
            self._pending = torch.zeros(*batch, self.agents, dtype=torch.float64, device=device)
            self._last_agent = torch.zeros(batch, dtype=torch.int64, device=device)
        return self._pending, self._last_agent

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        batch = tensordict_reset.batch_size
        reset = reset_flags(tensordict, self.reset_key, batch)
        self._counters(batch, tensordict_reset.device)
        self._finished = self._finished & ~reset.to(self._finished.device)
        if self._returns is not None and self._returns.numel() == reset.numel():
            restarted = reset.reshape(-1).cpu()
            self._returns = torch.where(restarted, 0.0, self._returns)
            self._taught = self._taught & ~restarted
        if self.agent_key is not None:
            pending, last = self._agent_state(batch, tensordict_reset.device)
            r = reset.to(pending.device)
            self._pending = torch.where(r.unsqueeze(-1), 0.0, pending)
            self._last_agent = torch.where(r, 0, last)
        zero = torch.zeros(*batch, 1, dtype=self._reward_dtype(), device=tensordict_reset.device)
        tensordict_reset.set(self.env_reward_key, zero)
        if self.estimate_key is not None:
            tensordict_reset.set(self.estimate_key, torch.zeros_like(zero, dtype=_float_dtype(zero.dtype)))
        return tensordict_reset

    def _reward_dtype(self) -> torch.dtype:
        parent = self.parent
        if parent is None:
            return torch.get_default_dtype()
        return parent.full_reward_spec[self.reward_key].dtype

    def _reset_on_native_autoreset(
        self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase
    ) -> TensorDictBase:
        return self._reset(tensordict, tensordict_reset)

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Fuse a stored trajectory ``[*B, T]`` after the fact (the class docstring; one agent per board)."""
        if self.agent_key is not None:
            raise ValueError("FeedbackFusion offline fuses one agent per board; it was built with agent_key")
        names = tensordict.names if tensordict.batch_dims else []
        if tensordict.batch_dims == 0 or (
            "time" in names and names.index("time") != tensordict.batch_dims - 1
        ):
            raise ValueError(
                f"FeedbackFusion offline needs data [*B, T] with time as the last dimension, got batch "
                f"{tuple(tensordict.batch_size)} with names {names}"
            )
        nxt = tensordict.get("next")
        reward = nxt.get(self.env_reward_key, None)
        if reward is None:
            reward = nxt.get(self.reward_key)
        human = self._human(tensordict, nxt, reward)
        done = self._done(nxt).to(torch.int64)
        episodes = done.cumsum(-1) - done
        nxt.set(self.reward_key, self._fuse(reward, human, episodes))
        nxt.set(self.env_reward_key, reward)
        return tensordict

    def _estimate_spec(self, shape: torch.Size, device: torch.device | None) -> Unbounded:
        return Unbounded(shape=(*shape, 1), dtype=_float_dtype(self._reward_dtype()), device=device)

    def transform_observation_spec(self, observation_spec: TensorSpec) -> TensorSpec:
        if not isinstance(observation_spec, Composite):
            raise TypeError(
                f"FeedbackFusion expects a Composite observation spec, got {type(observation_spec)}"
            )
        parent = self.parent
        if parent is None:
            raise RuntimeError("FeedbackFusion specs need the transform to sit in a TransformedEnv")
        observation_spec[self.env_reward_key] = parent.full_reward_spec[self.reward_key].clone()
        if self.estimate_key is not None:
            observation_spec[self.estimate_key] = self._estimate_spec(
                observation_spec.shape, observation_spec.device
            )
        return observation_spec

    def transform_input_spec(self, input_spec: TensorSpec) -> TensorSpec:
        if self.estimate_key is None:
            return input_spec
        state = input_spec["full_state_spec"]
        if state is None:
            state = Composite(shape=input_spec.shape, device=input_spec.device)
        state[self.estimate_key] = self._estimate_spec(input_spec.shape, input_spec.device)
        input_spec["full_state_spec"] = state
        return input_spec

    def transform_reward_spec(self, reward_spec: TensorSpec) -> TensorSpec:
        if self.scheme == "none":
            return reward_spec
        spec = reward_spec[self.reward_key]
        if not isinstance(spec, Unbounded) or not spec.dtype.is_floating_point:
            reward_spec[self.reward_key] = Unbounded(
                shape=spec.shape, dtype=_float_dtype(spec.dtype), device=spec.device
            )
        return reward_spec

    def get_extra_state(self) -> dict[str, Any]:
        """Episode counters, the agents' pending estimates and the schedule's state, for checkpoints."""
        return {
            "episodes": None if self._episodes is None else self._episodes.tolist(),
            "finished": None if self._finished is None else self._finished.tolist(),
            "pending": None if self._pending is None else self._pending.tolist(),
            "last_agent": None if self._last_agent is None else self._last_agent.tolist(),
            "returns": None if self._returns is None else self._returns.tolist(),
            "taught": None if self._taught is None else self._taught.tolist(),
            "schedule": self.schedule.state_dict(),
        }

    def set_extra_state(self, state: dict[str, Any]) -> None:
        self.schedule.load_state_dict(state["schedule"])
        if state["episodes"] is None:
            self._episodes = self._finished = None
        else:
            self._episodes = torch.tensor(state["episodes"], dtype=torch.int64)
            self._finished = torch.tensor(state["finished"], dtype=torch.bool)
        pending, last = state.get("pending"), state.get("last_agent")
        self._pending = None if pending is None else torch.tensor(pending, dtype=torch.float64)
        self._last_agent = None if last is None else torch.tensor(last, dtype=torch.int64)
        returns, taught = state.get("returns"), state.get("taught")
        self._returns = None if returns is None else torch.tensor(returns, dtype=torch.float64)
        self._taught = None if taught is None else torch.tensor(taught, dtype=torch.bool)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(scheme={self.scheme!r}, weight={self.schedule!r}, "
            f"estimate_key={self.estimate_key!r}, feedback_key={self.feedback_key!r})"
        )


ACTION_SPACES = ("categorical", "one-hot")


def action_space_of(action_space: str | None, spec: TensorSpec | None, action_key: NestedKey) -> str:
    """``"categorical"`` or ``"one-hot"``: as named, or as ``spec`` (the action's, or a Composite holding it)
    says, the way TorchRL's ``QValueModule`` reads its ``action_space``/``spec``; neither: categorical."""
    named = None if action_space is None else action_space.replace("_", "-")
    if named is not None and named not in ACTION_SPACES:
        raise ValueError(
            f"FusionModule action_space={action_space!r} is invalid; allowed: {', '.join(ACTION_SPACES)}"
        )
    from_spec = None
    if spec is not None:
        if isinstance(spec, Composite):
            spec = spec.get(action_key, None)
            if spec is None:
                raise KeyError(f"FusionModule spec has no {action_key!r} entry; pass the action's spec")
        if isinstance(spec, OneHot):
            from_spec = "one-hot"
        elif isinstance(spec, Categorical):
            from_spec = "categorical"
        else:
            raise ValueError(
                f"FusionModule spec {type(spec).__name__} is invalid; allowed: OneHot, Categorical"
            )
    if named is not None and from_spec is not None and named != from_spec:
        raise ValueError(
            f"FusionModule action_space={action_space!r} contradicts its spec, which is {from_spec}"
        )
    return named or from_spec or "categorical"


class FusionModule(TensorDictModuleBase):
    """The decision face of a :class:`Fusion`, for a policy: R and H^ of every action in, fused values out.

    Reads R (``env_values_key``), H^ (``human_values_key``), the mask (``action_mask_key``; absent: every
    action valid) and, if present, the game-ending actions (``terminal_key``) and each row's learner
    (``learner_key``); writes the fused values (``fused_values_key``) and each row's weight
    (``fusion_weight_key``), and with ``select="greedy"`` also the action (``action_key``): the best
    choosable action (the first on ties, a game-ending one only when all are), as an index
    (``action_space="categorical"``) or a one-hot vector (``"one-hot"``), or as ``spec`` says (TorchRL's
    ``QValueModule`` convention; e.g. ``spec=env.action_spec`` of a ``GymEnv``, one-hot by default). Without
    ``select`` the learner chooses from the fused values itself (Sarsa's epsilon-greedy, PG's softmax). The
    keys default to :mod:`hfrl_torch.keys`' names.

    Values are ``[*B, A]`` with any batch ``B``, none included (an unbatched env: ``[A]``, a weight ``[]``);
    rows of a multi-dimensional batch are flattened in order for the fusion's learners and match count.

    :param fusion: the fusion (its rule, weights and match count, shared with the loop that updates them).
    :param select: ``"greedy"`` or None.
    :param count: count each decision in the fusion's match count (the trust factor's m).
    :param weight_key: read each row's weight from this key instead of the fusion's schedule.
    :param action_space: ``"categorical"`` or ``"one-hot"`` (None: from ``spec``, else categorical).
    :param spec: the action's spec (or a Composite with an ``action_key`` entry): OneHot or Categorical.

    Example:
        >>> env = GymEnv("CartPole-v1")  # a one-hot action spec, no batch dimension
        >>> fuse = FusionModule(fusion, "greedy", env_values_key="action_value", spec=env.action_spec)
        >>> policy = TensorDictSequential(q_net, human_values, fuse)
    """

    def __init__(
        self,
        fusion: Fusion,
        select: str | None = None,
        count: bool = True,
        weight_key: NestedKey | None = None,
        *,
        env_values_key: NestedKey = keys.ENV_VALUES,
        human_values_key: NestedKey = keys.HUMAN_VALUES,
        action_mask_key: NestedKey = keys.ACTION_MASK,
        terminal_key: NestedKey = keys.AFTERSTATE_TERMINAL,
        learner_key: NestedKey = keys.LEARNER,
        fused_values_key: NestedKey = keys.FUSED_VALUES,
        fusion_weight_key: NestedKey = keys.FUSION_WEIGHT,
        action_key: NestedKey = keys.ACTION,
        action_space: str | None = None,
        spec: TensorSpec | None = None,
    ) -> None:
        super().__init__()
        if select not in (None, "greedy"):
            raise ValueError(f"FusionModule select={select!r} is invalid; allowed: None, greedy")
        self.fusion, self.select, self.count, self.weight_key = fusion, select, bool(count), weight_key
        self.action_space = action_space_of(action_space, spec, action_key)
        self.action_dtype = torch.int64
        if spec is not None:
            action_spec = spec.get(action_key) if isinstance(spec, Composite) else spec
            self.action_dtype = action_spec.dtype
        # the fusion's own key of each entry it reads, and where this module finds it
        self._reads = {
            keys.ENV_VALUES: env_values_key,
            keys.HUMAN_VALUES: human_values_key,
            keys.ACTION_MASK: action_mask_key,
            keys.AFTERSTATE_TERMINAL: terminal_key,
            keys.LEARNER: learner_key,
        }
        self.env_values_key, self.human_values_key = env_values_key, human_values_key
        self.fused_values_key, self.fusion_weight_key, self.action_key = (
            fused_values_key,
            fusion_weight_key,
            action_key,
        )
        self.in_keys = [
            env_values_key,
            human_values_key,
            action_mask_key,
            *([weight_key] if weight_key else []),
        ]
        self.out_keys = [fused_values_key, fusion_weight_key, *([action_key] if select else [])]
        self._own_keys = all(k == v for k, v in self._reads.items()) and (
            (fused_values_key, fusion_weight_key, action_key)
            == (keys.FUSED_VALUES, keys.FUSION_WEIGHT, keys.ACTION)
        )

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        human = tensordict.get(self.human_values_key)
        if self._own_keys and human.ndim == 2 and self.action_space == "categorical":
            self._fuse_rows(tensordict, tensordict)  # the fusion's own layout: no view needed
            return tensordict
        batch = human.shape[:-1]
        entries = {own: tensordict.get(key, None) for own, key in self._reads.items()}
        present = {own: value for own, value in entries.items() if value is not None}
        rows = TensorDict(present, batch_size=batch).reshape(-1)
        self._fuse_rows(tensordict, rows)
        tensordict.set(self.fused_values_key, rows.get(keys.FUSED_VALUES).reshape(*batch, -1))
        tensordict.set(self.fusion_weight_key, rows.get(keys.FUSION_WEIGHT).reshape(batch))
        if self.select == "greedy":
            tensordict.set(self.action_key, self._action(rows.get(keys.ACTION), human.shape))
        return tensordict

    def _fuse_rows(self, tensordict: TensorDictBase, rows: TensorDictBase) -> None:
        """Fuse ``rows`` ([M] rows of the fusion's own keys) and, with ``select``, write the index action."""
        weight = None if self.weight_key is None else tensordict.get(self.weight_key).reshape(-1)
        self.fusion.fuse(rows, count=self.count, weight=weight)
        if self.select == "greedy":
            values = rows.get(keys.FUSED_VALUES)
            mask = rows.get(keys.ACTION_MASK, None)
            mask = torch.ones(values.shape, dtype=torch.bool, device=values.device) if mask is None else mask
            keep = choosable(mask.to(torch.bool), rows.get(keys.AFTERSTATE_TERMINAL, None))
            rows.set(keys.ACTION, greedy_placement(values, keep))

    def _action(self, index: Tensor, shape: torch.Size) -> Tensor:
        """The chosen actions ``[M]`` as the env takes them: indices ``[*B]`` or one-hot ``[*B, A]``."""
        if self.action_space == "one-hot":
            return torch.nn.functional.one_hot(index, shape[-1]).reshape(shape).to(self.action_dtype)
        return index.reshape(shape[:-1]).to(self.action_dtype)
