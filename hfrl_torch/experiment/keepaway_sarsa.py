"""Keepaway keepers that learn by SMDP Sarsa(lambda) from the environment alone: ``train.py domain=keepaway
agent=sarsa``.

``agent.learners`` independent *learners* (teams of keepers: the seeds of the experiment) each play on
``agent.fields_per_learner`` fields of one batched ``KeepawayEnv`` (``sync="any"``: every field runs on
while others decide, so no field idles). Field f belongs to learner f // fields_per_learner; keeper k of
it reads and updates the weight table (f // fields_per_learner) * keepers + k (its own tile-coded
weights; one per learner with ``share_weights``), and learns from its own decisions only (thesis
Figure 5.4), each field giving each keeper its own SMDP transitions, pending action and traces (state
slot f * keepers + k):

* at a keeper's first decision in an episode, RLstartEpisode;
* at its later decisions, RLstep with reward = cycles since its own last decision (the env's
  ``reward``, which is about the deciding keeper);
* when the episode ends, RLendEpisode for every keeper with a pending action, with its entry of the
  env's ``episode_end_rewards`` (cycles since its last decision).

With fields_per_learner = 1 this is the reference (one field per team). With more, a table takes the
updates of several fields in the same step, summed (``index_add_``) rather than applied one after the
other as a single simulator would: a departure from the reference's sequential updates.

A learner's simulated clock is the experience of all its fields summed (each field's finished episodes
plus its current episode's cycles): the ``hours`` budget and the curves use it. Curves of the episode
duration (simulated seconds, each learner's mean, then the mean over learners with a 95 % interval) go
to TensorBoard and ``metrics.jsonl`` against simulated time per learner (step = simulated seconds) and,
in ``tensorboard/by_episodes``, against episodes per learner. Checkpoints hold the weights and every
finished episode; a resumed run abandons the episodes that were in progress (their learning so far is
kept) and starts new ones.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from tqdm import tqdm

from hfrl_torch import keys
from hfrl_torch.agents.sarsa import SarsaLambda, trace_capacity
from hfrl_torch.agents.sarsa.fused_keepers import KEEPAWAY_SCHEMES, FusedKeepers
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.logger import flatten_config, markdown_table
from hfrl_torch.common.stats import summarize
from hfrl_torch.common.validation import require_bool, require_choice, require_float, require_int
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv
from hfrl_torch.feedback.credit import GammaDelay
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.models.tile_coding import MAX_SIZE, TileCoding, keepaway_tile_widths
from hfrl_torch.trainers.keepaway_oracle import KeepawayOracle
from hfrl_torch.trainers.keepaway_replay import KeepawayReplay

CYCLES_PER_SECOND = 10
CYCLES_PER_MINUTE = 60 * CYCLES_PER_SECOND
CYCLES_PER_HOUR = 3600 * CYCLES_PER_SECOND
MAX_TABLE_GIB = 16.0  # refuse configs whose weight tables alone would need more memory than this


# ---------------------------------------------------------------------------------- agent


def make_sarsa_keepers(
    config: KeepawayConfig,
    learners: int,
    *,
    fields_per_learner: int = 1,
    alpha: float = 0.125,
    epsilon: float = 0.01,
    lambda_: float = 0.0,
    gamma: float = 1.0,
    tilings: int = 32,
    size: int = 2**20,
    min_trace: float = 0.01,
    max_traces: int | None = None,
    share_weights: bool = False,
    seed: int = 0,
    device: str | torch.device = "cpu",
) -> SarsaLambda:
    """Sarsa(lambda) keepers for ``learners`` teams of ``fields_per_learner`` fields each, tile-coded with
    the reference's widths. Agent rows (pending action, traces) are per field and keeper, f * keepers +
    k; weight tables are per team and keeper, (f // fields_per_learner) * keepers + k, or per team with
    ``share_weights`` (the keepers of a team share it, the reference's "hive mind")."""
    n = config.keepers
    slots = torch.arange(learners * fields_per_learner * n)
    team = slots // n // fields_per_learner
    coder = TileCoding(
        keepaway_tile_widths(n, config.takers),
        num_actions=config.num_actions,
        learners=learners if share_weights else learners * n,
        tilings=tilings,
        size=size,
        device=device,
    )
    tables = team if share_weights else team * n + slots % n
    return SarsaLambda(coder, alpha, epsilon, lambda_, gamma, min_trace, max_traces, seed=seed, tables=tables)


# -------------------------------------------------------------------------------- records


class KeepawayRecords:
    """Every finished episode of every field, each field's simulated clock and each learner's (the sum
    of its ``fields_per_learner`` fields' clocks; field f belongs to learner f // fields_per_learner).

    One row per episode: field, ordinal (its number within the learner), the learner's clock at its end
    (cycles), duration (cycles), HoldBall decisions, then the decisions of each keeper.
    """

    FIELD, ORDINAL, END, DURATION, HOLDS = range(5)

    def __init__(self, fields: int, keepers: int, fields_per_learner: int = 1) -> None:
        if fields < 1 or fields_per_learner < 1 or fields % fields_per_learner:
            raise ValueError(f"{fields} fields do not split into learners of {fields_per_learner} fields")
        self.fields, self.keepers, self.fields_per_learner = fields, keepers, fields_per_learner
        self.learners = fields // fields_per_learner
        self.finished_cycles = torch.zeros(fields, dtype=torch.int64)  # clock at the current episode's start
        self.clock = torch.zeros(fields, dtype=torch.int64)
        self.episodes = torch.zeros(self.learners, dtype=torch.int64)
        self.holds = torch.zeros(fields, dtype=torch.int64)  # of the episode in progress
        self.decisions = torch.zeros(fields, keepers, dtype=torch.int64)  # of the episode in progress
        self._rows: list[torch.Tensor] = [torch.zeros(0, 5 + keepers, dtype=torch.int64)]

    @property
    def table(self) -> torch.Tensor:
        """All rows [E, 5 + keepers] int64, in the order the episodes ended."""
        if len(self._rows) > 1:
            self._rows = [torch.cat(self._rows)]
        return self._rows[0]

    @property
    def learner_clock(self) -> torch.Tensor:
        """Simulated cycles of each learner [L]: its fields' clocks summed."""
        return self.clock.view(self.learners, self.fields_per_learner).sum(1)

    def learner_of(self, fields: torch.Tensor) -> torch.Tensor:
        """The learner of each field index in ``fields``."""
        return torch.div(fields, self.fields_per_learner, rounding_mode="floor")

    def decided(self, fields: torch.Tensor, keeper: torch.Tensor, action: torch.Tensor) -> None:
        """Count one decision of ``keeper`` [M] (action [M]) on each of the distinct ``fields`` [M]."""
        fields = fields.cpu()
        self.decisions[fields, keeper.cpu()] += 1
        self.holds[fields] += (action.cpu() == 0).long()

    def advance(self, episode_cycles: torch.Tensor) -> None:
        """Set the clocks from the cycles [B] of the episodes in progress (or just ended)."""
        self.clock = self.finished_cycles + episode_cycles.cpu()

    def finish(self, ended: torch.Tensor, durations: torch.Tensor) -> None:
        """Record the episodes that ended on fields ``ended`` [B] with ``durations`` [B] cycles; call
        :meth:`advance` with the same step's cycles first, so that the learners' clocks include them."""
        rows = ended.cpu().nonzero().squeeze(-1)
        duration = durations.cpu()[rows]
        learner = self.learner_of(rows)
        _, counts = torch.unique_consecutive(learner, return_counts=True)  # rows ascending: learners too
        starts = torch.repeat_interleave(counts.cumsum(0) - counts, counts)
        ordinal = self.episodes[learner] + torch.arange(rows.numel()) - starts
        self.finished_cycles[rows] += duration
        self.clock[rows] = self.finished_cycles[rows]
        end = self.learner_clock[learner]
        row = torch.cat(
            (torch.stack((rows, ordinal, end, duration, self.holds[rows]), 1), self.decisions[rows]), 1
        )
        self._rows.append(row)
        self.episodes.index_add_(0, learner, torch.ones_like(learner))
        self.holds[rows] = 0
        self.decisions[rows] = 0

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Tensors that restore the records (the episodes in progress are not kept)."""
        return {"rows": self.table.clone(), "clock": self.clock.clone(), "episodes": self.episodes.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Continue after the saved records, with fresh episodes starting at the saved clocks."""
        if state["clock"].shape != self.clock.shape or state["episodes"].shape != self.episodes.shape:
            raise ValueError(
                f"records of {state['clock'].numel()} fields / {state['episodes'].numel()} learners cannot "
                f"continue as {self.fields} fields / {self.learners} learners"
            )
        self._rows = [state["rows"].clone()]
        self.clock = state["clock"].clone()
        self.finished_cycles = state["clock"].clone()
        self.episodes = state["episodes"].clone()
        self.holds.zero_()
        self.decisions.zero_()

    def summary(self, rows: torch.Tensor) -> dict[str, float]:
        """Episode duration over learners (each learner's mean in seconds over its fields' episodes,
        then mean and 95 % interval over learners), HoldBall share and decisions per episode of each
        keeper, for the episodes ``rows``."""
        table = rows.double()
        learner = self.learner_of(rows[:, self.FIELD])
        count = torch.bincount(learner, minlength=self.learners)
        total = torch.zeros(self.learners, dtype=torch.float64).index_add_(
            0, learner, table[:, self.DURATION]
        )
        seen = count > 0
        per_learner = total[seen] / count[seen] / CYCLES_PER_SECOND
        s = summarize(per_learner, floor=0.0)
        decisions = table[:, 5:]
        out = {
            "episode_s_mean": s["mean"],
            "episode_s_ci95_low": s["ci95_low"],
            "episode_s_ci95_high": s["ci95_high"],
            "episode_s_median_of_learners": s["median"],
            "learners": float(s["n"]),
            "episodes": float(table.shape[0]),
            "hold_share": float(table[:, self.HOLDS].sum() / decisions.sum().clamp(min=1)),
        }
        for k in range(self.keepers):
            out[f"decisions_per_episode_keeper{k}"] = float(decisions[:, k].mean())
        return out

    def time_window(self, start: int, stop: int) -> dict[str, float] | None:
        """Summary of the episodes that ended at learner clock [start, stop) cycles (None if none did)."""
        t = self.table
        rows = t[(t[:, self.END] >= start) & (t[:, self.END] < stop)]
        return self.summary(rows) if rows.shape[0] else None

    def episode_window(self, start: int, stop: int) -> dict[str, float]:
        """Summary of every learner's episodes number start..stop-1."""
        t = self.table
        return self.summary(t[(t[:, self.ORDINAL] >= start) & (t[:, self.ORDINAL] < stop)])


# ---------------------------------------------------------------------------------- loop


def run_sarsa_keepers(
    env: KeepawayEnv,
    agent: SarsaLambda,
    records: KeepawayRecords,
    *,
    cycles: int = 0,
    episodes: int = 0,
    on_step: Callable[[KeepawayRecords], None] | None = None,
    human: FusedKeepers | None = None,
    watch: Callable[[TensorDictBase], None] | None = None,
) -> KeepawayRecords:
    """Play and learn until every learner's clock reaches ``cycles`` or every learner has finished
    ``episodes`` episodes (0 = no such limit), calling ``on_step`` after each env step.

    Works with either ``sync`` mode of the env: only the fields flagged ``"deciding"`` choose (agent row
    field * keepers + keeper); the others' actions are ignored by the env. With ``human`` (one field per
    learner), a trainer watches every field, H^ learns from its feedback and the keepers choose by the
    fusion rule (:class:`FusedKeepers`). ``watch`` sees every step's tensordict (with its ``"next"``)
    before the fields that ended restart: a live view, pacing for a person.
    """
    if cycles <= 0 and episodes <= 0:
        raise ValueError("run_sarsa_keepers needs a budget: cycles > 0 or episodes > 0")
    fields, n = env.batch_size[0], env.config.keepers
    if records.fields != fields:
        raise ValueError(f"records of {records.fields} fields for an env of {fields}")
    every_keeper = torch.arange(n, device=env.device)
    td = env.reset()
    reward = torch.zeros(fields, device=env.device)  # of the step that led to each field's decision
    action = torch.zeros(fields, dtype=torch.int64, device=env.device)
    records.advance(td[keys.EPISODE_CYCLES])

    def budget_left() -> bool:
        by_time = cycles > 0 and bool((records.learner_clock < cycles).any())
        by_episodes = episodes > 0 and bool((records.episodes < episodes).any())
        return (cycles <= 0 or by_time) and (episodes <= 0 or by_episodes)

    if human is not None and records.fields_per_learner != 1:
        raise ValueError("a trainer watches one field per learner: fields_per_learner must be 1")
    if human is not None and human.trainer is not None:
        human.trainer.new_episodes(torch.ones(fields, dtype=torch.bool))

    while budget_left():
        rows = td[keys.DECIDING].nonzero().squeeze(-1)
        if rows.numel():
            keeper = td[keys.KEEPER][rows]
            obs, mask = td[keys.OBSERVATION][rows], td[keys.ACTION_MASK][rows]
            if human is None:
                chosen = agent.decide(rows * n + keeper, obs, mask, reward[rows])
            else:
                slots = rows * n + keeper
                bonus = human.shaping(slots).to(device=reward.device, dtype=reward.dtype)
                fuse = human.fuse(rows, keeper, mask)
                chosen = agent.decide(
                    slots, obs, mask, reward[rows] + bonus, fuse=fuse, explore=human.explores
                )
                clock = records.clock.double() / CYCLES_PER_SECOND
                human.decided(rows, keeper, chosen, agent.chosen_tiles, obs, clock)
            records.decided(rows, keeper, chosen)
            action = action.index_put((rows,), chosen)
        td[keys.ACTION] = action
        td, td_next = env.step_and_maybe_reset(td)
        if watch is not None:
            watch(td)
        after = td["next"]
        ended = after[keys.DONE].view(-1)
        reward = torch.where(ended, 0.0, after[keys.REWARD].view(-1))  # a restarted field's keeper starts
        records.advance(after[keys.EPISODE_CYCLES])
        if human is not None:
            human.deliver(records.clock.double() / CYCLES_PER_SECOND)
        if bool(ended.any()):
            done_rows = ended.nonzero().squeeze(-1)
            slots = (done_rows.unsqueeze(1) * n + every_keeper).reshape(-1)
            end_rewards = after[keys.EPISODE_END_REWARDS][done_rows].reshape(-1)
            if human is not None:
                end_rewards = end_rewards + human.shaping(slots).to(end_rewards)
                lasted = after[keys.EPISODE_CYCLES].view(-1)[done_rows]
                human.end_episodes(done_rows, lasted.double() / CYCLES_PER_SECOND)
            agent.end_episode(slots, end_rewards)
            records.finish(ended, after[keys.EPISODE_CYCLES])
        td = td_next
        records.advance(td[keys.EPISODE_CYCLES])
        if on_step is not None:
            on_step(records)
    return records


# --------------------------------------------------------------------------------- config


def check_sarsa(cfg: DictConfig) -> None:
    """Check ``agent`` for Sarsa keepers (and that the domain is keepaway with >= 3v2)."""
    require_choice(cfg, "domain.name", ("keepaway",))
    require_choice(cfg, "agent.name", ("sarsa",))
    learners = require_int(cfg, "agent.learners", 1, 100_000)
    per_learner = require_int(cfg, "agent.fields_per_learner", 1, 100_000)
    if learners * per_learner > 1_000_000:
        raise ConfigError(
            f"agent.learners={learners} x agent.fields_per_learner={per_learner} fields is over 1,000,000"
        )
    hours = require_float(cfg, "agent.hours", 0.0, 10_000.0)
    episodes = require_int(cfg, "agent.episodes", 0)
    if hours == 0 and episodes == 0:
        raise ConfigError("agent.hours=0 and agent.episodes=0 leave no budget; set one of them > 0")
    require_float(cfg, "agent.alpha", 1e-12)
    require_float(cfg, "agent.epsilon", 0.0, 1.0)
    require_float(cfg, "agent.lambda", 0.0, 1.0)
    require_float(cfg, "agent.gamma", 1e-9, 1.0)
    tilings = require_int(cfg, "agent.tilings", 1, 1024)
    bits = require_int(cfg, "agent.table_bits", 1, int(math.log2(MAX_SIZE)))
    require_float(cfg, "agent.min_trace", 1e-12, 1.0)
    share = require_bool(cfg, "agent.share_weights")
    keepers = require_int(cfg, "domain.keepers", 3, 11)
    takers = require_int(cfg, "domain.takers", 2, 11)
    from hfrl_torch.experiment.evaluate import keepaway_kernels

    keepaway_kernels(cfg)
    active = tilings * (4 * keepers + 2 * takers - 3)
    if OmegaConf.select(cfg, "agent.max_traces") is not None:
        require_int(cfg, "agent.max_traces", active, 10_000_000)
    require_float(cfg, "agent.log_minutes", 0.02)  # >= 12 cycles: one TensorBoard step per second
    require_int(cfg, "agent.log_episodes", 1)
    require_float(cfg, "agent.checkpoint_minutes", 0.01)
    tables = learners if share else learners * keepers
    slots = learners * per_learner * keepers  # pending action and traces per field and keeper
    max_traces = OmegaConf.select(cfg, "agent.max_traces")
    lambda_, gamma, min_trace = float(cfg.agent["lambda"]), float(cfg.agent.gamma), float(cfg.agent.min_trace)
    capacity = (
        int(max_traces) if max_traces is not None else trace_capacity(active, gamma * lambda_, min_trace)
    )
    gib = (tables * 2**bits * 4 + slots * capacity * 12) / 2**30
    if gib > MAX_TABLE_GIB:
        raise ConfigError(
            f"agent.learners={learners} x agent.fields_per_learner={per_learner} need {tables} tables of "
            f"2^{bits} weights and {slots} x {capacity} trace slots, {gib:.1f} GiB (limit "
            f"{MAX_TABLE_GIB:.0f}); lower agent.learners, agent.fields_per_learner or agent.table_bits"
        )


KEEPAWAY_TRAINERS = ("none", "oracle", "replay", "interactive")


def check_keepaway_feedback(cfg: DictConfig) -> None:
    """Check ``fusion``, ``trainer`` and ``human`` for keepers taught by a trainer (thesis Chapter 5)."""
    from hfrl_torch.experiment.factories import check_human, make_weight_schedule

    fusion = require_choice(cfg, "fusion.name", KEEPAWAY_SCHEMES)
    trainer = cfg.trainer.name
    if trainer not in KEEPAWAY_TRAINERS:
        raise ConfigError(
            f"trainer={trainer} is not available for keepaway yet; allowed: {', '.join(KEEPAWAY_TRAINERS)}"
        )
    if trainer == "none":
        if fusion != "none":
            raise ConfigError(
                f"fusion={fusion} fuses a trainer's H^ with Q; choose trainer=oracle (or fusion=none)"
            )
        return
    if trainer == "interactive":
        from hfrl_torch.interactive.live import check_interactive

        check_interactive(cfg)
        if int(cfg.agent.learners) != 1:
            raise ConfigError(
                f"agent.learners={cfg.agent.learners} with trainer=interactive: one person teaches one team "
                "of keepers on one field; allowed: 1 (what train.py sets when the command line leaves it out)"
            )
    if int(cfg.agent.fields_per_learner) != 1:
        raise ConfigError(
            f"agent.fields_per_learner={cfg.agent.fields_per_learner} with a trainer: one trainer watches "
            "one field, so each learner plays one field; allowed: 1"
        )
    check_human(cfg, "tile_coded")
    make_weight_schedule(cfg, 1)
    fusion_scaling(cfg)
    if trainer == "interactive":
        return
    if trainer == "replay":
        if not OmegaConf.select(cfg, "trainer.log"):
            raise ConfigError("trainer=replay needs trainer.log=<feedback log file>")
        return
    reference = OmegaConf.select(cfg, "trainer.reference")
    if reference not in (None, "hand") and not Path(str(reference)).exists():
        raise ConfigError(
            f"trainer.reference={reference!r} is invalid; allowed: null or hand (the hand-coded keepers), "
            "or a keepaway run directory or checkpoint"
        )
    require_float(cfg, "trainer.frequency", 0.0, 1.0)
    require_float(cfg, "trainer.consistency", 0.0, 1.0)
    require_float(cfg, "trainer.reaction", 1e-6)
    if require_bool(cfg, "trainer.timing.enabled"):
        require_float(cfg, "trainer.timing.delay_shape", 1e-6)
        require_float(cfg, "trainer.timing.delay_scale", 1e-6)
        if OmegaConf.select(cfg, "trainer.timing.fatigue_tau") is not None:
            require_float(cfg, "trainer.timing.fatigue_tau", 1e-6)
        require_float(cfg, "trainer.timing.positive_bias", 0.0, 1.0)
        require_float(cfg, "trainer.timing.absence", 0.0, 1.0)
        if OmegaConf.select(cfg, "trainer.timing.tail_lines") is not None:
            raise ConfigError(
                "trainer.timing.tail_lines is a Tetris option (lines per game); keepaway allows only null"
            )


def fusion_scaling(cfg: DictConfig) -> str:
    """How keepaway puts Q and H^ on one scale: ``fusion.normalise`` true (per decision, as in Tetris), false
    (raw), ``spread`` or null (the keepaway default, ``spread``); see :class:`FusedKeepers`."""
    value = OmegaConf.select(cfg, "fusion.normalise")
    if value is None or value == "spread":
        return "spread"
    if isinstance(value, bool):
        return "decision" if value else "none"
    raise ConfigError(f"fusion.normalise={value!r} is invalid; allowed: true, false, spread, null")


def _reference_keepers(
    cfg: DictConfig, config: KeepawayConfig
) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None:
    """The oracle's reference: None (the hand-coded keepers) or a learned checkpoint's greedy keepers as
    ``(obs, keeper) -> actions`` (field f is judged against the checkpoint's team f % its teams)."""
    from hfrl_torch.agents.sarsa.policy import load_keeper_policy
    from hfrl_torch.common.checkpoint import load_checkpoint

    reference = OmegaConf.select(cfg, "trainer.reference")
    if reference in (None, "hand"):
        return None
    ckpt = load_checkpoint(str(reference), domain="keepaway")
    if (ckpt["domain_config"]["keepers"], ckpt["domain_config"]["takers"]) != (config.keepers, config.takers):
        raise ConfigError(
            f"trainer.reference={reference!r} learned {ckpt['domain_config']['keepers']}v"
            f"{ckpt['domain_config']['takers']}, not {config.keepers}v{config.takers}"
        )
    choose, _ = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(int(cfg.seed) + 7))

    def reference_actions(obs: torch.Tensor, keeper: torch.Tensor) -> torch.Tensor:
        return choose(obs, torch.ones(obs.shape[0], config.num_actions, dtype=torch.bool), keeper)

    return reference_actions


def _human_from_config(
    cfg: DictConfig,
    config: KeepawayConfig,
    agent: SarsaLambda,
    log: FeedbackLog | None,
    session: Any = None,
) -> FusedKeepers:
    """H^ on the Sarsa keepers' tile coding, the trainer (the simulated oracle, or with trainer=interactive
    the person on the page of ``session``, a ``TeachingSession``) and the fusion rule of ``cfg``."""
    from hfrl_torch.experiment.factories import make_credit, make_weight_schedule

    fields, n = int(cfg.agent.learners), config.keepers
    per_keeper = cfg.human.model == "keeper"
    coder = agent.coder
    model = TileCoding(
        coder.widths.tolist(),
        num_actions=coder.num_actions,
        learners=fields * n if per_keeper else fields,
        tilings=coder.tilings,
        size=coder.size,
        device=coder.weight.device,
    )
    tamer = KeeperTamer(
        model,
        fields,
        alpha=float(cfg.human.alpha),
        credit=make_credit(cfg),
        window=float(cfg.human.window),
        history=int(cfg.human.history),
        renormalise=bool(cfg.human.renormalise),
    )
    t = cfg.trainer
    if t.name == "interactive":
        from hfrl_torch.interactive.keepaway_live import BrowserKeeperTrainer

        if session is None:
            raise ValueError("trainer=interactive needs the page's session")
        trainer = BrowserKeeperTrainer(session, fields, log)
    elif t.name == "replay":
        trainer = KeepawayReplay.from_log(str(t.log), fields, log)
    else:
        timing = t.timing
        on = bool(timing.enabled)
        trainer = KeepawayOracle(
            n,
            config.takers,
            frequency=float(t.frequency),
            consistency=float(t.consistency),
            delay=GammaDelay(float(timing.delay_shape), float(timing.delay_scale))
            if on
            else float(t.reaction),
            seed=int(cfg.seed) * 2 + 1,
            log=log,
            fatigue_tau=None if not on or timing.fatigue_tau is None else float(timing.fatigue_tau),
            positive_bias=float(timing.positive_bias) if on else 0.0,
            absence=float(timing.absence) if on else 0.0,
            reference=_reference_keepers(cfg, config),
        )
    rows = torch.arange(fields * n)
    owners = rows if per_keeper else torch.div(rows, n, rounding_mode="floor")
    return FusedKeepers(
        cfg.fusion.name,
        make_weight_schedule(cfg, fields),
        tamer,
        trainer,
        n,
        owners,
        scaling=fusion_scaling(cfg),
        seed=int(cfg.seed) * 2 + 3,
    )


def _agent_from_config(cfg: DictConfig, config: KeepawayConfig, device: torch.device) -> SarsaLambda:
    a = cfg.agent
    return make_sarsa_keepers(
        config,
        a.learners,
        fields_per_learner=a.fields_per_learner,
        alpha=a.alpha,
        epsilon=a.epsilon,
        lambda_=a["lambda"],
        gamma=a.gamma,
        tilings=a.tilings,
        size=2**a.table_bits,
        min_trace=a.min_trace,
        max_traces=a.max_traces,
        share_weights=a.share_weights,
        seed=int(cfg.seed),
        device=device,
    )


# ---------------------------------------------------------------------------------- train


def train_sarsa(cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> dict[str, float]:
    """``train.py domain=keepaway agent=sarsa``: train, log the curves, checkpoint; returns the last
    point of the curve against simulated time."""
    from hfrl_torch.experiment.evaluate import keepaway_config
    from hfrl_torch.experiment.factories import make_device, make_run_logger

    check_sarsa(cfg)
    check_keepaway_feedback(cfg)
    a = cfg.agent
    config = keepaway_config(cfg)
    device = make_device(cfg)
    agent = _agent_from_config(cfg, config, device)
    taught = cfg.trainer.name != "none"
    person = cfg.trainer.name == "interactive"  # a person's presses cannot be regenerated: fsync each
    log = FeedbackLog(run_dir / "feedback.jsonl", session=run_dir.name, fsync=person) if taught else None
    teaching = None
    if person:
        from hfrl_torch.interactive.live import start_live_teaching

        teaching = start_live_teaching(cfg, log, view="keepaway")
    session = None if teaching is None else teaching.session
    human = _human_from_config(cfg, config, agent, log, session) if taught else None
    fields = a.learners * a.fields_per_learner
    records = KeepawayRecords(fields, config.keepers, a.fields_per_learner)
    history: list[dict[str, float]] = []
    resumes = time_windows = episode_windows = 0  # windows: points of the two curves closed so far
    if checkpoint is not None:
        state = checkpoint["state"]
        agent.load_state_dict(state["agent"])
        agent.forget_episodes()
        records.load_state_dict(state["records"])
        if human is not None:
            human.load_state_dict(state["human"])
        history = list(checkpoint["history"])
        resumes = int(state["resumes"]) + 1
        time_windows, episode_windows = int(state["time_windows"]), int(state["episode_windows"])
    env = KeepawayEnv(fields, config, device=device, seed=int(cfg.seed) + 1_000_003 * resumes, sync="any")
    watch = None
    if teaching is not None and human is not None:
        from hfrl_torch.interactive.keepaway_live import wait_for_teacher, watch_field

        watch = watch_field(env, records, human, curve_every=int(a.log_episodes))
        wait_for_teacher(cfg, teaching)

    window = max(1, round(a.log_minutes * CYCLES_PER_MINUTE))
    every = max(1, round(a.checkpoint_minutes * CYCLES_PER_MINUTE))
    saved_at = int(records.learner_clock.min())
    logger = make_run_logger(
        cfg, str(run_dir / "tensorboard"), purge_step=_seconds(time_windows * window) + 1 if resumes else None
    )
    episode_logger = make_run_logger(
        cfg,
        str(run_dir / "tensorboard" / "by_episodes"),
        purge_step=episode_windows * a.log_episodes + 1 if resumes else None,
    )
    if not resumes:
        logger.text("hyperparameters", markdown_table(flatten_config(cfg)))
        logger.text(
            "axes",
            "by_hours/*: step = simulated seconds per learner (its fields' experience summed); "
            "by_episodes/* (run by_episodes): step = episodes per learner. Every point: mean over "
            f"{a.learners} learners ({a.fields_per_learner} fields each) of each learner's mean episode "
            "duration, with its 95 % interval.",
        )
        if human is not None:
            if person:
                who = (
                    "human:browser: a PERSON teaching in the browser (trainer=interactive), watching field 0"
                )
            elif cfg.trainer.name == "replay":
                who = f"replay: the events of {cfg.trainer.log}, given again on each field's clock"
            else:
                reference = cfg.trainer.reference or "hand"
                who = (
                    f"{KeepawayOracle.source}: a SIMULATED trainer (Griffith et al.'s oracle against the "
                    f"{reference} keepers, L={cfg.trainer.frequency}, C={cfg.trainer.consistency}), "
                    "not a person"
                )
            logger.text(
                "trainer",
                f"{who}; fusion={cfg.fusion.name}, credit={cfg.human.credit}, H^ per {cfg.human.model}",
            )
    metrics_file = run_dir / "metrics.jsonl"
    ckpt_path = run_dir / "checkpoints" / LAST
    config_yaml = OmegaConf.to_yaml(cfg, resolve=True)
    budget_cycles = round(a.hours * CYCLES_PER_HOUR)

    def save() -> None:
        save_checkpoint(
            ckpt_path,
            domain="keepaway",
            agent="sarsa",
            config_yaml=config_yaml,
            payload={
                "state": {
                    "agent": agent.state_dict(),
                    "records": records.state_dict(),
                    "resumes": resumes,
                    "time_windows": time_windows,
                    "episode_windows": episode_windows,
                    **({"human": human.state_dict()} if human is not None else {}),
                },
                "history": history,
                "policy": {
                    "kind": "tile_sarsa",
                    "tile_widths": agent.coder.widths.tolist(),
                    "tilings": agent.coder.tilings,
                    "size": agent.coder.size,
                    "num_actions": agent.coder.num_actions,
                    "learners": "(field // fields_per_learner) * keepers + keeper",
                    "fields_per_learner": a.fields_per_learner,
                    "teams": int(a.learners),
                    "share_weights": bool(a.share_weights),
                    "human": None
                    if human is None
                    else {
                        "scheme": human.scheme,
                        "model": str(cfg.human.model),
                        "scaling": human.scaling,
                        "q_spread": human.q_spread.tolist(),
                        "weight": human.schedule.value().tolist(),
                    },
                },
                "domain_config": asdict(config),
            },
        )

    def write(record: dict[str, float]) -> None:
        history.append(record)
        with metrics_file.open("a") as f:
            f.write(json.dumps(record) + "\n")

    teams = f"{a.learners} learners x {a.fields_per_learner} fields"
    desc = f"Sarsa keepers {config.keepers}v{config.takers}, {teams}"
    if budget_cycles > 0:
        initial, total, unit = _seconds(int(records.learner_clock.min())), round(a.hours * 3600), "sim s"
    else:
        initial, total, unit = int(records.episodes.min()), a.episodes, "episode"
    bar = tqdm(total=total, initial=initial, unit=unit, desc=desc, dynamic_ncols=True, mininterval=1.0)
    start_wall, start_clock = time.perf_counter(), int(records.clock.sum())

    def on_step(rec: KeepawayRecords) -> None:
        nonlocal time_windows, episode_windows, saved_at
        slowest = int(rec.learner_clock.min())
        while slowest >= (time_windows + 1) * window:
            stats = rec.time_window(time_windows * window, (time_windows + 1) * window)
            time_windows += 1
            if stats is None:  # no episode ended in this window on any field
                continue
            wall = time.perf_counter() - start_wall
            stats["field_cycles_per_s"] = (int(rec.clock.sum()) - start_clock) / max(wall, 1e-9)
            for k in range(rec.keepers):
                stats[f"decisions_total_keeper{k}"] = float(rec.table[:, 5 + k].sum()) / rec.learners
            if human is not None:
                stats.update(human.stats())
            end = time_windows * window
            logger.scalars(stats, _seconds(end), prefix="by_hours/")
            write({"axis": "hours", "hours": end / CYCLES_PER_HOUR, "sim_seconds": _seconds(end), **stats})
            bar.set_postfix(episode_s=f"{stats['episode_s_mean']:.2f}", hold=f"{stats['hold_share']:.2f}")
        while int(rec.episodes.min()) >= (episode_windows + 1) * a.log_episodes:
            lo = episode_windows * a.log_episodes
            stats = rec.episode_window(lo, lo + a.log_episodes)
            if human is not None:
                stats.update(human.stats())
            episode_windows += 1
            episode_logger.scalars(stats, lo + a.log_episodes, prefix="by_episodes/")
            write({"axis": "episodes", "episode": lo + a.log_episodes, **stats})
        if slowest - saved_at >= every:
            save()
            logger.flush()
            episode_logger.flush()
            saved_at = slowest
        position = _seconds(slowest) if budget_cycles > 0 else int(rec.episodes.min())
        if position > bar.n:
            bar.update(position - bar.n)

    try:
        run_sarsa_keepers(
            env,
            agent,
            records,
            cycles=budget_cycles,
            episodes=a.episodes,
            on_step=on_step,
            human=human,
            watch=watch,
        )
    finally:
        bar.close()
        if teaching is not None:
            teaching.stop()
        save()
        episode_logger.close()
        if log is not None:
            log.close()
    axis = "hours" if budget_cycles > 0 else "episodes"  # the curve of the budget's axis
    points = [h for h in history if h["axis"] == axis]
    if points:
        final = dict(points[-1])
    elif records.table.shape[0]:  # a run shorter than one point of its curve: all its episodes
        final = {"axis": axis, "episode": int(records.episodes.min()), **records.summary(records.table)}
    else:
        final = {}
    if final:
        final["hours"] = int(records.learner_clock.min()) / CYCLES_PER_HOUR
        final["wall_s"] = time.perf_counter() - start_wall
        if human is not None:
            final["feedback_events"] = float(human.feedback.sum())
        logger.hparams(flatten_config(cfg), {"hparam/episode_s_last": final["episode_s_mean"]})
    logger.close()
    return final


def _seconds(cycles: int) -> int:
    return cycles // CYCLES_PER_SECOND
