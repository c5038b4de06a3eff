"""Sarsa keepers taught by a trainer at the same time: H^ learned from credited feedback, fused with Q.

The thesis's Chapter 5 experiment. One trainer watches each field (the whole team, as one person would); at
each decision of a keeper with the ball it may judge the decision (:class:`KeepawayOracle`), and its event
arrives after a reaction delay. Due events go to :class:`KeeperTamer`, which spreads them over the field's
recent decisions (gamma(2.0, 0.28) credit over 500 ms, or all to the previous decision) and updates H^ on the
same tile coding as Q. The keepers choose by the fusion scheme:

* ``none``: Q (the trainer still watches and H^ still learns: the environment-only control);
* ``human_only``: argmax H^, greedy with random ties (TAMER);
* ``linear`` / ``action_biasing`` / ``annealed``: Q + w H^; ``exponential``: Q (1 + sign(H^) |H^|^w). Q is in
  cycles (tens) and H^ in feedback units (about 1), so ``scaling`` puts them on one scale first: ``spread``
  (default) multiplies H^ by the learner's running mean of max_a Q - min_a Q over its decisions (H^ = 1 is
  worth what Q typically separates the actions by), ``decision`` rescales both to [0, 1] over each
  decision's available actions, ``none`` fuses the raw values. The exponential rule scales Q by a factor
  of H^ alone, so it needs no common scale: under ``spread`` it takes the raw values (Q >= 0 here);
* ``control_sharing``: argmax H^ with probability min(w, 1), else Q;
* ``reward_shaping``: Q chooses, and Sarsa learns from r + w H^(s, a) of its previous decision.

Exploration (epsilon-greedy) applies to the fused values. Sarsa always learns from its own Q of the action
taken. The weight w per learner is the trust factor (eq. 4.4 once per episode, from the episode's hold time
and the match rate m: the share of its decisions where argmax H^ = argmax Q, counting only decisions where
H^ prefers some action), annealed, or fixed.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import torch
from torch import Tensor

from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.fusion.schedules import WeightSchedule
from hfrl_torch.fusion.schemes import FUSIONS, fuse_values, rescale_range

KEEPAWAY_SCHEMES = FUSIONS  # every fusion option works in keepaway
_VALUE_RULE = {"annealed": "linear", "action_biasing": "linear"}
SCALINGS = ("spread", "decision", "none")
MIN_SPREAD = 1.0  # cycles: H^ keeps a say before Q has learned to separate the actions


class KeeperTrainer(Protocol):
    """Who judges the keepers (``KeepawayOracle``, or a person through the browser, who also has ``poll``)."""

    source: str

    def new_episodes(self, starting: Tensor) -> None: ...

    def give(
        self, obs: Tensor, action: Tensor, deciding: Tensor, time: Tensor, keeper: Tensor | None = None
    ) -> tuple[Tensor, Tensor]: ...

    def state_dict(self) -> dict[str, Any]: ...

    def load_state_dict(self, state: dict[str, Any]) -> None: ...


class FusedKeepers:
    """The trainer, H^ and the fusion rule around Sarsa keepers, for B fields with one learner each.

    :param scheme: one of ``KEEPAWAY_SCHEMES``.
    :param schedule: the weight w of each of the B learners (trust, annealed or fixed).
    :param tamer: H^ and its credit assignment over the B fields.
    :param trainer: who judges the decisions (a simulated oracle, a person); None: nobody (H^ stays 0).
    :param keepers: n, the keepers per field.
    :param owners: [B * keepers] the H^ model of each agent row (field * keepers + keeper).
    :param scaling: ``spread``, ``decision`` or ``none`` (see the module docstring).
    :param spread_rate: the step of the running mean of the Q spread (``spread``).
    :param seed: seed of control sharing's draws.
    :param queue: feedback events per field that may wait for their arrival time.
    """

    def __init__(
        self,
        scheme: str,
        schedule: WeightSchedule,
        tamer: KeeperTamer,
        trainer: KeeperTrainer | None,
        keepers: int,
        owners: Tensor,
        scaling: str = "spread",
        seed: int = 0,
        queue: int = 32,
        spread_rate: float = 0.01,
    ) -> None:
        if scaling not in SCALINGS:
            raise ValueError(f"scaling={scaling!r} is invalid; allowed: {', '.join(SCALINGS)}")
        if scheme not in KEEPAWAY_SCHEMES:
            raise ValueError(
                f"fusion {scheme!r} is invalid for keepaway; allowed: {', '.join(KEEPAWAY_SCHEMES)}"
            )
        fields = tamer.tiles.shape[0]
        if schedule.learners != fields or owners.shape != (fields * keepers,):
            raise ValueError(
                f"FusedKeepers: {fields} fields need a schedule of {fields} learners and "
                f"{fields * keepers} owners"
            )
        self.scheme, self.schedule, self.tamer, self.trainer = scheme, schedule, tamer, trainer
        self.keepers, self.fields = keepers, fields
        self.owners = owners.to(torch.int64)
        self.scaling, self.spread_rate = scaling, float(spread_rate)
        self.q_spread = torch.full((fields,), MIN_SPREAD, dtype=torch.float64)
        self.generator = torch.Generator().manual_seed(seed)
        self.pending_value = torch.zeros(fields, queue, dtype=torch.float64)
        self.pending_time = torch.full((fields, queue), torch.inf, dtype=torch.float64)
        self.h_last = torch.zeros(fields * keepers, dtype=torch.float64)  # H^ of each row's pending action
        self.matches = torch.zeros(fields, dtype=torch.int64)  # of the episode in progress
        self.compared = torch.zeros(fields, dtype=torch.int64)
        self.feedback = torch.zeros(fields, dtype=torch.int64)  # events delivered, per learner, all episodes
        self.positive = torch.zeros(fields, dtype=torch.int64)
        self.followed_human = 0
        self.early = 0  # events delivered before their time because a field's queue was full
        self._h = torch.zeros(0, 0, dtype=torch.float64)  # H^ of the last decide's rows, for decided()

    # ------------------------------------------------------------------ choosing

    @property
    def explores(self) -> bool:
        """Whether the keepers explore (epsilon-greedy); TAMER's human-only keepers act greedily."""
        return self.scheme != "human_only"

    def weights(self, fields: Tensor) -> Tensor:
        """The current weight w of the learners of ``fields`` [M] (float64)."""
        return self.schedule.value().to(torch.float64)[fields.cpu()]

    def fuse(self, fields: Tensor, keeper: Tensor, mask: Tensor) -> Callable[[Tensor, Tensor], Tensor]:
        """The ``fuse(Q, tiles)`` of ``SarsaLambda.decide`` for decisions on ``fields`` [M] by ``keeper`` [M]
        with available actions ``mask`` [M, A]; it also counts the match of argmax H^ and argmax Q."""
        rows = fields * self.keepers + keeper
        owners = self.owners[rows.cpu()].to(self.tamer.model.weight.device)
        w = self.weights(fields)

        def fused(q: Tensor, tiles: Tensor) -> Tensor:
            h = self.tamer.values(owners, tiles).to(torch.float64).cpu()
            qc, mk = q.to(torch.float64).cpu(), mask.cpu().to(torch.bool)
            self._h = h
            self._count_matches(fields.cpu(), qc, h, mk)
            if self.scheme in ("none", "reward_shaping"):
                return q
            if self.scheme == "human_only":
                return h.to(q.device)
            if self.scheme == "control_sharing":
                follow = torch.rand(h.shape[0], generator=self.generator, dtype=torch.float64) < w.clamp(
                    max=1.0
                )
                self.followed_human += int(follow.sum())
                return torch.where(follow.unsqueeze(1), h, qc).to(q.device)
            if self.scaling == "decision":
                r, hh = rescale_range(qc, mk), rescale_range(h, mk)
            elif self.scaling == "spread" and self.scheme != "exponential":
                r, hh = qc, h * self._spread(fields.cpu(), qc, mk).unsqueeze(1)
            else:
                r, hh = qc, h
            return fuse_values(r, hh, _VALUE_RULE.get(self.scheme, self.scheme), w).to(q.device)

        return fused

    def _spread(self, fields: Tensor, q: Tensor, mask: Tensor) -> Tensor:
        """Update each learner's running mean Q spread with these decisions; returns it per row."""
        gap = q.masked_fill(~mask, -torch.inf).amax(1) - q.masked_fill(~mask, torch.inf).amin(1)
        choice = mask.sum(1) > 1
        target = torch.zeros_like(self.q_spread).index_add_(0, fields[choice], gap[choice])
        count = torch.zeros_like(self.q_spread).index_add_(0, fields[choice], torch.ones_like(gap[choice]))
        seen = count > 0
        mean_gap = torch.where(seen, target / count.clamp(min=1), self.q_spread)
        moved = (1 - self.spread_rate) * self.q_spread + self.spread_rate * mean_gap
        self.q_spread = torch.where(seen, moved, self.q_spread).clamp(min=MIN_SPREAD)
        return self.q_spread[fields]

    def _count_matches(self, fields: Tensor, q: Tensor, h: Tensor, mask: Tensor) -> None:
        hi = h.masked_fill(~mask, -torch.inf).amax(1)
        lo = h.masked_fill(~mask, torch.inf).amin(1)
        prefers = hi > lo
        same = h.masked_fill(~mask, -torch.inf).argmax(1) == q.masked_fill(~mask, -torch.inf).argmax(1)
        self.compared.index_add_(0, fields, prefers.long())
        self.matches.index_add_(0, fields, (prefers & same).long())

    # ------------------------------------------------------------------ feedback

    def shaping(self, rows: Tensor) -> Tensor:
        """The reward bonus w H^(s, a) of each agent row's previous decision (reward_shaping; else 0)."""
        if self.scheme != "reward_shaping":
            return torch.zeros(rows.shape[0], dtype=torch.float64)
        r = rows.cpu()
        return self.weights(torch.div(r, self.keepers, rounding_mode="floor")) * self.h_last[r]

    def decided(
        self, fields: Tensor, keeper: Tensor, action: Tensor, chosen_tiles: Tensor, obs: Tensor, time: Tensor
    ) -> None:
        """After ``SarsaLambda.decide``: remember the decisions in H^'s history and let the trainer judge
        them. ``fields``/``keeper``/``action`` [M]; ``chosen_tiles`` [M, N]; ``obs`` [M, F]; ``time`` [B]
        each field's simulated clock (seconds)."""
        b, f = self.fields, fields.cpu()
        deciding = torch.zeros(b, dtype=torch.bool)
        deciding[f] = True
        rows = f * self.keepers + keeper.cpu()
        chosen_h = self._h.gather(1, action.cpu().view(-1, 1)).squeeze(1) if self._h.numel() else None
        if chosen_h is not None:
            self.h_last[rows] = chosen_h
        n = chosen_tiles.shape[-1]
        tiles = torch.zeros(b, n, dtype=torch.int64)
        tiles[f] = chosen_tiles.cpu()
        owner = torch.zeros(b, dtype=torch.int64)
        owner[f] = self.owners[rows]
        self.tamer.record(deciding, owner, tiles, time.cpu())
        if self.trainer is None:
            return
        full_obs = torch.zeros(b, obs.shape[-1], dtype=obs.dtype)
        full_obs[f] = obs.cpu()
        full_action = torch.zeros(b, dtype=torch.int64)
        full_action[f] = action.cpu()
        full_keeper = torch.zeros(b, dtype=torch.int64)
        full_keeper[f] = keeper.cpu()
        values, times = self.trainer.give(full_obs, full_action, deciding, time.cpu(), full_keeper)
        self._enqueue(values, times)

    def _enqueue(self, values: Tensor, times: Tensor) -> None:
        new = values != 0
        if not bool(new.any()):
            return
        full = new & torch.isfinite(self.pending_time).all(1)
        if bool(full.any()):  # deliver the oldest waiting event of those fields now
            slot = self.pending_time.argmin(1)
            self._deliver_slots(full, slot)
            self.early += int(full.sum())
        slot = torch.isinf(self.pending_time).to(torch.int8).argmax(1)
        rows = new.nonzero().squeeze(-1)
        self.pending_value[rows, slot[rows]] = values[rows]
        self.pending_time[rows, slot[rows]] = times[rows]

    def deliver(self, clock: Tensor) -> None:
        """Give H^ every waiting event whose arrival time has come on its field's clock [B] (seconds).

        A trainer with a ``poll(clock) -> (values [B], times [B])`` method (a person, whose presses come
        whenever they come) is asked for its new events first."""
        poll = getattr(self.trainer, "poll", None)
        while poll is not None:
            values, times = poll(clock)
            if not bool((values != 0).any()):
                break
            self._enqueue(values, times)
        due = self.pending_time <= clock.cpu().to(torch.float64).unsqueeze(1)
        while bool(due.any()):
            fields = due.any(1)
            slot = torch.where(due, self.pending_time, torch.inf).argmin(1)
            self._deliver_slots(fields, slot)
            due[fields, slot[fields]] = False

    def _deliver_slots(self, fields: Tensor, slot: Tensor) -> None:
        rows = fields.nonzero().squeeze(-1)
        values = torch.zeros(self.fields, dtype=torch.float64)
        times = torch.zeros(self.fields, dtype=torch.float64)
        values[rows] = self.pending_value[rows, slot[rows]]
        times[rows] = self.pending_time[rows, slot[rows]]
        self.tamer.give(values, times)
        self.feedback.index_add_(0, rows, torch.ones_like(rows))
        self.positive.index_add_(0, rows, (values[rows] > 0).long())
        self.pending_time[rows, slot[rows]] = torch.inf
        self.pending_value[rows, slot[rows]] = 0.0

    # ------------------------------------------------------------------ episodes

    def end_episodes(self, fields: Tensor, seconds: Tensor) -> None:
        """Eq. 4.4 (or annealing) for the learners whose episode ended on ``fields`` [E], lasting ``seconds``
        [E]; then new episodes start there (the trainer may leave or come back)."""
        f = fields.cpu()
        ended = torch.zeros(self.fields, dtype=torch.bool)
        ended[f] = True
        perf = torch.zeros(self.fields, dtype=torch.float64)
        perf[f] = seconds.cpu().to(torch.float64)
        rate = torch.where(self.compared > 0, self.matches / self.compared.clamp(min=1), torch.nan)
        if self.schedule.kind == "trust":
            self.schedule.end_episode(perf, rate.to(torch.float64), ended)
        else:
            self.schedule.end_episode(ended=ended)
        self.matches[f] = 0
        self.compared[f] = 0
        rows = (f.unsqueeze(1) * self.keepers + torch.arange(self.keepers)).reshape(-1)
        self.h_last[rows] = 0.0
        if self.trainer is not None:
            self.trainer.new_episodes(ended)

    def stats(self) -> dict[str, float]:
        """Per-learner means of the weight and of the feedback so far, and H^'s credited share."""
        w = self.schedule.value().to(torch.float64)
        return {
            "fusion/weight_mean": float(w.mean()),
            "fusion/q_spread_mean": float(self.q_spread.mean()),
            "feedback/events_per_learner": float(self.feedback.double().mean()),
            "feedback/positive_share": float(self.positive.sum() / self.feedback.sum().clamp(min=1)),
            "feedback/credited_share": self.tamer.credited_share,
            "feedback/early_deliveries": float(self.early),
        }

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict[str, Any]:
        """H^, the schedule, the trainer and the counters (pending events and histories are not kept)."""
        return {
            "human_weight": self.tamer.model.weight.clone(),
            "schedule": self.schedule.state_dict(),
            "trainer": None if self.trainer is None else self.trainer.state_dict(),
            "generator": self.generator.get_state(),
            "feedback": self.feedback.clone(),
            "positive": self.positive.clone(),
            "tamer_counts": [self.tamer.decisions, self.tamer.credited],
            "followed_human": self.followed_human,
            "q_spread": self.q_spread.clone(),
            "early": self.early,
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue after a saved state: episodes in progress are abandoned, waiting feedback is dropped."""
        try:
            self.tamer.model.weight.copy_(state["human_weight"])
            self.schedule.load_state_dict(state["schedule"])
            if self.trainer is not None:
                self.trainer.load_state_dict(state["trainer"])
            self.generator.set_state(state["generator"])
            self.feedback.copy_(state["feedback"])
            self.positive.copy_(state["positive"])
            decisions, credited = state["tamer_counts"]
            self.followed_human, self.early = int(state["followed_human"]), int(state["early"])
            self.q_spread = state["q_spread"].to(torch.float64).clone()
        except (KeyError, TypeError, RuntimeError, ValueError) as e:
            raise CheckpointError(f"bad keepaway human-feedback state in the checkpoint ({e!r})") from None
        self.tamer.decisions, self.tamer.credited = int(decisions), int(credited)
