"""Keepaway steps re-laid as each keeper's own SMDP transitions, the layout a plain TorchRL loss expects.

:class:`~hfrl_torch.envs.keepaway.env.KeepawayEnv` takes turns: a step's ``action`` is the decision of the
keeper named in ``keeper``, but the step's ``("next", "reward")`` is the reward of the keeper that decides
*next* (the cycles since its own previous decision), and at an episode's end every keeper's last decision
is owed ``episode_end_rewards[k]``. A TorchRL loss reads ``(observation, action, next reward, next
observation)`` row by row, so on the raw steps it pairs one keeper's action with another keeper's reward
and bootstraps from another keeper's state. :func:`keeper_transitions` pairs each decision of keeper k with
the cycles until k's next decision (its reward) and k's next decision's observation, or with
``episode_end_rewards[k]`` and a terminal flag when the episode ends first: the transitions Sarsa keepers
learn from (Stone, Sutton & Kuhlmann 2005), which ``DQNLoss``, ``QValueActor`` and replay buffers take as
they are. This is TorchRL's replay-side pattern (like ``MultiStepTransform``), not nested ``("agents", ...)``
keys: only one keeper acts per step, so a per-agent row of every step would hold n - 1 keepers that did not
act, which a plain loss cannot skip.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase

from hfrl_torch import keys

__all__ = ["TRANSITION_KEYS", "keeper_transitions"]

# what each transition holds (and its "next" twin for the observation-side keys)
TRANSITION_KEYS = (keys.OBSERVATION, keys.ACTION_MASK, keys.KEEPER, keys.EPISODE_CYCLES)


def keeper_transitions(rollout: TensorDictBase) -> TensorDict:
    """Each keeper's complete decisions in ``rollout`` ``[*B, T]`` (time last, as ``env.rollout`` and
    collectors lay it out) as ``[N]`` transitions, field by field and in time order.

    A transition holds ``observation``, ``action_mask``, ``keeper``, ``episode_cycles`` and ``action`` of the
    decision, and under ``"next"``: ``reward`` ``[N, 1]`` (the cycles until the same keeper's next decision,
    or its ``episode_end_rewards`` entry), ``done`` and ``terminated`` ``[N, 1]`` (the episode ended first),
    and the observation-side keys of that next decision (of the decision itself where the episode ended). A
    decision still open when the rollout stops is left out (a later rollout does not complete it).
    """
    if rollout.batch_dims < 1:
        raise ValueError("keeper_transitions needs a rollout [*B, T] with time last, got no batch dimension")
    steps = rollout.reshape(-1, rollout.batch_size[-1]) if rollout.batch_dims != 2 else rollout
    nxt = steps.get("next")
    deciding = steps.get(keys.DECIDING).reshape(steps.batch_size).tolist()
    keeper = steps.get(keys.KEEPER).reshape(steps.batch_size).tolist()
    done = nxt.get(keys.DONE).reshape(steps.batch_size).tolist()
    reward = nxt.get(keys.REWARD).reshape(steps.batch_size).tolist()
    end_rewards = nxt.get(keys.EPISODE_END_REWARDS).tolist()
    starts: list[tuple[int, int]] = []  # (field, step) of each transition's decision
    ends: list[tuple[int, int]] = []  # (field, step) of the same keeper's next decision (its own at the end)
    rewards: list[float] = []
    terminal: list[bool] = []
    for b in range(steps.batch_size[0]):
        open_: dict[int, int] = {}  # keeper -> step of its decision awaiting its reward
        for t in range(steps.batch_size[1]):
            if deciding[b][t]:
                k = keeper[b][t]
                if k in open_:  # its previous decision's reward arrived with this step's observation
                    starts.append((b, open_[k]))
                    ends.append((b, t))
                    rewards.append(reward[b][t - 1])
                    terminal.append(False)
                open_[k] = t
            if done[b][t]:
                for k, s in open_.items():
                    starts.append((b, s))
                    ends.append((b, s))
                    rewards.append(end_rewards[b][t][k])
                    terminal.append(True)
                open_ = {}
    return _gather(steps, starts, ends, rewards, terminal)


def _gather(
    steps: TensorDictBase,
    starts: list[tuple[int, int]],
    ends: list[tuple[int, int]],
    rewards: list[float],
    terminal: list[bool],
) -> TensorDict:
    """The transitions' entries taken from ``steps`` ``[F, T]`` at the decisions and their successors."""
    b0, t0 = (torch.tensor([s[i] for s in starts], dtype=torch.int64) for i in (0, 1))
    b1, t1 = (torch.tensor([e[i] for e in ends], dtype=torch.int64) for i in (0, 1))
    root = {k: steps.get(k)[b0, t0] for k in (*TRANSITION_KEYS, keys.ACTION)}
    ended = torch.tensor(terminal, dtype=torch.bool).unsqueeze(-1)
    nxt = {k: steps.get(k)[b1, t1] for k in TRANSITION_KEYS}
    nxt[keys.REWARD] = torch.tensor(rewards, dtype=torch.float32).unsqueeze(-1)
    nxt[keys.DONE], nxt[keys.TERMINATED] = ended, ended.clone()
    return TensorDict({**root, "next": TensorDict(nxt, [len(starts)])}, [len(starts)])
