"""SMDP Sarsa(lambda) with hashed tile coding, for many independent learners at once.

Stone, Sutton & Kuhlmann, "Reinforcement Learning for RoboCup Soccer Keepaway" (Adaptive Behavior
2005), as the thesis gives it in Figure 5.4 (RLstartEpisode, RLstep, RLendEpisode) and as the
reference keepaway players' ``LinearSarsaAgent`` implements it:

* Q(s, a) = sum of the weights of a's N active tiles; every weight with a trace moves by
  (alpha / N) * delta * e, so Q of a state whose tiles all have trace 1 moves by alpha * delta;
* epsilon-greedy over the available actions, ties of the greedy choice broken at random;
* replacing traces: traces decay by gamma * lambda at every SMDP step of the learner (and are dropped
  below ``min_trace``), the tiles of the other available actions are cleared and those of the
  chosen action set to 1;
* the reward of a step is whatever the caller passes (keepaway: cycles since the learner's last
  decision), the terminal value is 0.

Each row of a call names a learner (``learners`` [M], distinct); a learner has its pending action and
Q, its own traces and a weight table of the :class:`TileCoding` (its own by default; learners may
share one, as the reference's "hive mind" keepers share theirs). Rows of one call that share a table
are updated from the same weights and their changes summed (``index_add_``), not applied one after the
other.

Traces are sparse: per learner a bounded list of ``max_traces`` (tile index, value) slots, the
vectorised counterpart of the reference's ``nonzeroTraces`` list (``RL_MAX_NONZERO_TRACES`` =
100,000). The default capacity holds every trace that can still be >= ``min_trace``:
N * (1 + floor(log(min_trace) / log(gamma * lambda))) slots, i.e. N = 416 with the thesis's
lambda = 0 and 416 * 44 with lambda = 0.9, capped at 100,000. When the slots are full the smallest
traces are dropped first (the reference raises its minimum trace instead).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from hfrl_torch.models.tile_coding import TileCoding

MAX_TRACES = 100_000  # the reference's RL_MAX_NONZERO_TRACES, per learner


def trace_capacity(active_tiles: int, decay: float, min_trace: float) -> int:
    """Slots needed so that no trace >= ``min_trace`` is ever dropped: ``active_tiles`` per surviving
    decision, and a decision's traces survive floor(log(min_trace) / log(decay)) later decays."""
    if decay >= 1.0:
        return max(active_tiles, MAX_TRACES)
    if decay <= 0.0 or min_trace >= 1.0:
        return active_tiles
    survivals = math.floor(math.log(min_trace) / math.log(decay))
    return max(active_tiles, min(active_tiles * (1 + survivals), MAX_TRACES))


class SarsaLambda:
    """SMDP Sarsa(lambda) over a tile coder for a batch of learners (thesis Figure 5.4).

    :param coder: the tile coding and its weight tables (by default one per learner).
    :param alpha: step size, applied per weight as alpha / N (N active tiles of an action).
    :param epsilon: exploration probability of the epsilon-greedy choice.
    :param lambda_: trace decay per SMDP step (0 in the thesis).
    :param gamma: discount per SMDP step (1 in the thesis and the reference).
    :param min_trace: traces below this are dropped (the reference's 0.01).
    :param max_traces: trace slots per learner (``None``: :func:`trace_capacity`).
    :param seed: seed of the exploration and tie-breaking generator.
    :param tables: [L] the coder's weight table of each learner (default: learner l uses table l, so
        L = ``coder.learners``); learners that name one table share its weights (the reference's
        "hive mind"), while pending actions and traces stay per learner.
    """

    kernels = "torch"  # the reference path, any device (``SarsaLambdaNumba``: the compiled twin)
    # greedy ties: "random" (the reference's) or "first" (the lowest action, HoldBall, for comparisons with
    # players that break ties so); :meth:`select` draws the same numbers either way, as the compiled twin.
    ties = "random"

    def __init__(
        self,
        coder: TileCoding,
        alpha: float = 0.125,
        epsilon: float = 0.01,
        lambda_: float = 0.0,
        gamma: float = 1.0,
        min_trace: float = 0.01,
        max_traces: int | None = None,
        seed: int = 0,
        tables: torch.Tensor | None = None,
    ) -> None:
        if not alpha > 0 or not 0 <= epsilon <= 1 or not 0 <= lambda_ <= 1 or not 0 < gamma <= 1:
            raise ValueError(
                f"need alpha > 0, epsilon and lambda in [0, 1], gamma in (0, 1]; "
                f"got {alpha}, {epsilon}, {lambda_}, {gamma}"
            )
        if not 0 < min_trace <= 1:
            raise ValueError(f"min_trace must be in (0, 1], got {min_trace}")
        n = coder.active_tiles
        capacity = trace_capacity(n, gamma * lambda_, min_trace) if max_traces is None else max_traces
        if capacity < n:
            raise ValueError(f"max_traces must hold one action's {n} tiles, got {capacity}")
        self.coder = coder
        self.alpha, self.epsilon, self.lambda_, self.gamma = float(alpha), float(epsilon), lambda_, gamma
        self.min_trace = float(min_trace)
        device, dtype = coder.weight.device, coder.weight.dtype
        if tables is None:
            tables = torch.arange(coder.learners)
        if tables.dim() != 1 or int(tables.min()) < 0 or int(tables.max()) >= coder.learners:
            raise ValueError(f"tables must be [L] indices into the coder's {coder.learners} tables")
        self.tables = tables.to(device=device, dtype=torch.int64)
        learners = self.tables.shape[0]
        self.last_action = torch.full((learners,), -1, dtype=torch.int64, device=device)
        self.q_last = torch.zeros(learners, dtype=dtype, device=device)
        self.trace_index = torch.zeros(learners, capacity, dtype=torch.int64, device=device)
        self.trace_value = torch.zeros(learners, capacity, dtype=dtype, device=device)
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(seed)
        self.chosen_tiles = torch.zeros(0, coder.active_tiles, dtype=torch.int64, device=device)

    @property
    def learners(self) -> int:
        return self.tables.shape[0]

    @property
    def step_size(self) -> float:
        """alpha / N, the change of each active weight per unit of delta * trace."""
        return self.alpha / self.coder.active_tiles

    # ----------------------------------------------------------------------- acting

    def select(self, q: torch.Tensor, mask: torch.Tensor, explore: bool = True) -> torch.Tensor:
        """Epsilon-greedy actions [M] over Q [M, A] and available actions ``mask`` [M, A].

        With probability epsilon a uniformly random available action, otherwise the best one; ties
        of the best value are broken uniformly at random (both draws are made for every row, so the
        random stream does not depend on the choices).
        """
        m, a = q.shape
        tie_noise = torch.rand(m, a, generator=self.generator, device=q.device)
        random_noise = torch.rand(m, a, generator=self.generator, device=q.device)
        explore_draw = torch.rand(m, generator=self.generator, device=q.device)
        best = q.masked_fill(~mask, -torch.inf).amax(1, keepdim=True)
        if self.ties == "first":
            greedy = (mask & (q == best)).to(torch.int8).argmax(1)
        else:
            greedy = torch.where(mask & (q == best), tie_noise, -1.0).argmax(1)
        if not explore:
            return greedy
        uniform = torch.where(mask, random_noise, -1.0).argmax(1)
        return torch.where(explore_draw < self.epsilon, uniform, greedy)

    @torch.no_grad()
    def action_values(self, learners: torch.Tensor, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The active tiles [M, A, N] and Q [M, A] of each row's state (lines 1-3 / 11-13), for a caller that
        fuses Q with other values before :meth:`decide` chooses."""
        tiles = self.coder.tiles(obs)
        return tiles, self.coder(self.tables[learners], tiles)

    # ------------------------------------------------------- the three routines

    def start_episode(self, learners: torch.Tensor, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """RLstartEpisode (lines 1-8) for learners without a pending action; returns their actions."""
        if bool((self.last_action[learners] >= 0).any()):
            raise ValueError("start_episode: a learner still has a pending action (call end_episode first)")
        return self.decide(learners, obs, mask, torch.zeros(learners.shape[0]))

    def step(
        self, learners: torch.Tensor, reward: torch.Tensor, obs: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        """RLstep (lines 9-25) for learners with a pending action; returns their next actions."""
        if bool((self.last_action[learners] < 0).any()):
            raise ValueError("step: a learner has no pending action (call start_episode first)")
        return self.decide(learners, obs, mask, reward)

    @torch.no_grad()
    def decide(
        self,
        learners: torch.Tensor,
        obs: torch.Tensor,
        mask: torch.Tensor,
        reward: torch.Tensor,
        *,
        explore: bool = True,
        values: tuple[torch.Tensor, torch.Tensor] | None = None,
        choose_by: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """One decision per row: RLstartEpisode where the learner has no pending action, RLstep with
        ``reward`` (the SMDP step's reward, e.g. cycles since its last decision) where it has one.

        :param learners: [M] distinct learner indices.
        :param obs: [M, F] state variables of each learner's state s.
        :param mask: [M, A] available actions A^s.
        :param reward: [M] reward of the step that ended in s (ignored for starting learners).
        :param explore: epsilon-greedy (True) or greedy with random ties (False).
        :param values: the rows' ``(tiles, Q)`` from :meth:`action_values` (computed here if None).
        :param choose_by: [M, A] values to choose the action by instead of Q (a person's H^ fused in by
            ``hfrl_torch.fusion``); the update stays Sarsa's, with Q of the action taken.
        :returns: [M] the chosen actions (the new LastAction); their active tiles are left in
            ``chosen_tiles`` [M, N].
        """
        if torch.unique(learners).numel() != learners.numel():
            raise ValueError("decide: rows must name distinct learners")
        coder = self.coder
        dtype = coder.weight.dtype
        mask = mask.to(torch.bool)
        starting = self.last_action[learners] < 0
        tables = self.tables[learners]
        tiles, q = self.action_values(learners, obs) if values is None else values  # lines 1-3 / 11-13
        action = self.select(q if choose_by is None else choose_by, mask, explore)  # lines 4 / 14
        q_next = q.gather(1, action.unsqueeze(1)).squeeze(1)

        index, value = self.trace_index[learners], self.trace_value[learners]
        value = torch.where(starting.unsqueeze(1), 0.0, value)  # line 6: e = 0
        reward = reward.to(device=q.device, dtype=dtype)
        delta = reward - self.q_last[learners] + self.gamma * q_next  # lines 9-10, 16
        delta = torch.where(starting, 0.0, delta)
        coder.add_(tables, index, self.step_size * delta.unsqueeze(1) * value)  # line 17

        n = tiles.shape[-1]
        chosen = tiles.gather(1, action.view(-1, 1, 1).expand(-1, 1, n)).squeeze(1)  # F_LastAction [M, N]
        q_last = torch.where(starting, q_next, coder(tables, chosen))  # line 18 (start: line 3)
        value = value * (self.gamma * self.lambda_)  # line 19
        value = torch.where(value < self.min_trace, 0.0, value)
        others = mask & (torch.arange(mask.shape[1], device=mask.device) != action.unsqueeze(1))
        index, value = self._replace_traces(index, value, tiles, others, chosen)  # lines 20-25

        self.trace_index[learners], self.trace_value[learners] = index, value
        self.last_action[learners] = action  # line 4 / 14 (LastActionTime is the env's clock)
        self.q_last[learners] = q_last
        self.chosen_tiles = chosen
        return action

    @torch.no_grad()
    def end_episode(self, learners: torch.Tensor, reward: torch.Tensor) -> None:
        """RLendEpisode (lines 26-28) for learners with a pending action (others are left alone):
        delta = r - Q_LastAction, the terminal state being worth 0; the learner then has no pending
        action until its next start_episode."""
        pending = self.last_action[learners] >= 0
        reward = reward.to(device=self.q_last.device, dtype=self.q_last.dtype)
        delta = torch.where(pending, reward - self.q_last[learners], 0.0)
        index, value = self.trace_index[learners], self.trace_value[learners]
        self.coder.add_(self.tables[learners], index, self.step_size * delta.unsqueeze(1) * value)
        self.last_action[learners] = -1

    def forget_episodes(self) -> None:
        """Drop every pending action and trace (episodes in progress are abandoned, weights kept)."""
        self.last_action.fill_(-1)
        self.q_last.zero_()
        self.trace_value.zero_()

    # ------------------------------------------------------------------ traces

    def _replace_traces(
        self,
        index: torch.Tensor,
        value: torch.Tensor,
        tiles: torch.Tensor,
        others: torch.Tensor,
        chosen: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Clear the traces of the other available actions' tiles and set the chosen action's to 1.

        Slots are matched by tile index per row (a row-wise sort of the tiles to clear and a
        ``searchsorted`` per slot); the chosen tiles are deduplicated (hash collisions inside F_a) and
        merged in, keeping the ``capacity`` largest traces. When gamma * lambda < min_trace (the
        thesis's lambda = 0) every older trace has just been dropped, so the chosen tiles alone remain.
        """
        m, capacity = index.shape
        # rows sorted by one flat sort of keys offset by row * size (about twice as fast as a row-wise sort)
        offset = (torch.arange(m, device=chosen.device) * self.coder.size).unsqueeze(1)
        fresh = (chosen + offset).view(-1).sort().values.view(m, -1) - offset
        first = torch.ones_like(fresh, dtype=torch.bool)
        first[:, 1:] = fresh[:, 1:] != fresh[:, :-1]
        if self.gamma * self.lambda_ < self.min_trace:  # no trace survives the decay: skip the matching
            pad = capacity - fresh.shape[1]
            new_value = first.to(value.dtype)
            if pad:
                fresh = torch.cat((fresh, fresh.new_zeros(m, pad)), dim=1)
                new_value = torch.cat((new_value, new_value.new_zeros(m, pad)), dim=1)
            return fresh, new_value
        clear = torch.where(others.unsqueeze(-1), tiles, -1).reshape(m, -1)
        clear = torch.cat((clear, chosen), dim=1).sort(dim=1).values  # [M, (A + 1) N], rows ascending
        at = torch.searchsorted(clear, index).clamp(max=clear.shape[1] - 1)
        drop = clear.gather(1, at) == index
        value = torch.where(drop, 0.0, value)
        merged_index = torch.cat((index, fresh), dim=1)
        merged_value = torch.cat((value, first.to(value.dtype)), dim=1)
        kept = merged_value.topk(capacity, dim=1, sorted=False).indices
        return merged_index.gather(1, kept), merged_value.gather(1, kept)

    # --------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict[str, Any]:
        """Weights, pending actions, traces and the generator state (tensors and numbers only)."""
        return {
            "weight": self.coder.weight.clone(),
            "last_action": self.last_action.clone(),
            "q_last": self.q_last.clone(),
            "trace_index": self.trace_index.clone(),
            "trace_value": self.trace_value.clone(),
            "generator": self.generator.get_state(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore what :meth:`state_dict` saved (same number of learners, table size and traces)."""
        self.coder.weight.copy_(state["weight"])
        self.last_action.copy_(state["last_action"])
        self.q_last.copy_(state["q_last"])
        self.trace_index.copy_(state["trace_index"])
        self.trace_value.copy_(state["trace_value"])
        self.generator.set_state(state["generator"])
