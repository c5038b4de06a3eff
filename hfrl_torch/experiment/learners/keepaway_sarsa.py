"""Keepaway keepers that learn by SMDP Sarsa(lambda), from the environment and, with a trainer, from a
person's feedback too: ``train.py domain=keepaway [fusion=<scheme>]`` (thesis Figure 5.4 and Chapter 5).

``agent.learners`` independent *learners* (teams of keepers: the seeds of the experiment) each play on
``agent.fields_per_learner`` fields of one batched ``KeepawayEnv``. With one field per learner on the
whole-cycle kernels (``domain.kernels=cycle``, the CPU default) it runs ``sync="all"``: each field on its own
to its next decision in one compiled call, so every step decides on every field at once; otherwise
``sync="any"``: the fields in lock-step until any must decide, so none idles and a learner's fields do not
all decide from the same weights. Field f belongs to learner f // fields_per_learner;
keeper k of it reads and updates the weight table (f // fields_per_learner) * keepers + k, and learns from
its own decisions only, each field giving each keeper its own SMDP transitions (state slot f * keepers + k):
RLstartEpisode at its first decision, RLstep with reward = cycles since its own last decision, RLendEpisode
for every keeper with a pending action when the episode ends (``episode_end_rewards``).

With a trainer (one field per learner: one trainer watches each field, the whole team, as a person would),
each step of the loop, per field:

1. the feedback due on the field's simulated clock comes out of the channel into the step's tensordict and
   H^ (``KeeperTamer``, on the Sarsa keepers' own tiles) learns from it, credited over the decisions of the
   last 500 ms whichever keepers made them;
2. the deciding keeper's Q and H^ of every action go through the one fusion component, and Sarsa chooses
   epsilon-greedily on the fused values (greedily where a bandit chooses the weight of a rule that weighs
   H^: ``agent.greedy_with_bandit``), learning from its own Q of the action taken;
3. the decision enters H^'s history, and the trainer may judge it: its event goes into the channel;
4. the env's ``FeedbackFusion`` transform fuses the reward each keeper learns from (``reward_shaping``:
   r + w H^ of its previous decision; the environment's reward for every other scheme);
5. when an episode ends, the fusion ends the learner's episode: eq. 4.4 with the episode's hold time and
   the match rate m of argmax H^ and argmax Q over its decisions (or one annealing step).

A learner's simulated clock is the experience of all its fields summed: the ``hours`` budget and the curves
use it. Curves of the episode duration go to TensorBoard and ``metrics.jsonl`` against simulated time per
learner (step = simulated seconds) and, in ``tensorboard/by_episodes``, against episodes per learner.
Checkpoints hold everything in flight, so a run killed and resumed continues as if never stopped: the
simulator's fields (positions, world models, its generator), the env's bookkeeping, the keepers' pending SMDP
transitions and traces, H^ and its credit windows, the trainer's and the fusion's draws, the feedback
channel, the records of the episodes in progress, and the last feedback event learned from (the events
after it are given again and not logged twice). A checkpoint written before this (no ``play``) still loads,
with a warning: its episodes in progress are abandoned and the env is reseeded (weights, H^, fusion and
finished episodes are kept), so that run does not continue as the uninterrupted one would.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import TransformedEnv

from hfrl_torch import keys
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.common.checkpoint import CheckpointWarning
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.common.logger import Logger
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.envs.keepaway import KeepawayEnv
from hfrl_torch.envs.keepaway.records import (
    CYCLES_PER_HOUR,
    CYCLES_PER_MINUTE,
    CYCLES_PER_SECOND,
    KeepawayRecords,
)
from hfrl_torch.experiment.checks import check_keepaway_feedback, check_sarsa
from hfrl_torch.experiment.factories import (
    make_device,
    make_feedback_wiring,
    make_fusion,
    make_keepaway_config,
    make_keeper_tamer,
    make_keeper_trainer,
    make_keepers,
)
from hfrl_torch.experiment.learners.tetris_games import TRAINER_LABELS
from hfrl_torch.experiment.run import Learner, Point
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.fusion import changed_by_teaching
from hfrl_torch.fusion.transform import FeedbackFusion, FusionModule
from hfrl_torch.interactive.keepaway_live import BrowserKeeperTrainer, KeepawayWatcher, wait_for_teacher
from hfrl_torch.interactive.live import LiveTeaching, taught_by_person

STEPS_PER_CHUNK = 200  # env steps per chunk (each usually one simulator cycle)
# one row per finished episode of a taught learner: its human effort and the weight it was played at
EFFORT_COLUMNS = ("field", "episode", "events", "trainer_seconds", "weight")


class SarsaKeepers(Learner):
    """Sarsa keepers on B fields, taught by a trainer or not (see the module docstring)."""

    domain = "keepaway"
    agent = "sarsa"
    default_scaling = "spread"  # H^ times Q's running spread (docs/feedback.md)

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_sarsa(cfg)
        check_keepaway_feedback(cfg)

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        super().__init__(cfg, run_dir, checkpoint)
        a = cfg.agent
        self.config = config = make_keepaway_config(cfg)
        device = make_device(cfg)
        self.agent_sarsa = make_keepers(cfg, config, device)
        self.n = config.keepers
        self.fields = fields = int(a.learners) * int(a.fields_per_learner)
        self.records = KeepawayRecords(fields, self.n, int(a.fields_per_learner))
        self.taught = cfg.trainer.name != "none"
        self.person = cfg.trainer.name == "interactive"
        self.log: FeedbackLog | None = None
        self.teaching: LiveTeaching | None = None
        self.resumes = self.time_windows = self.episode_windows = 0  # windows: points closed so far
        if self.taught:
            self.fusion = make_fusion(cfg, type(self), fields)
            wiring = make_feedback_wiring(
                cfg,
                run_dir,
                self.fusion,
                lambda log: make_keeper_trainer(cfg, config, fields, log),
                lambda session, log: BrowserKeeperTrainer(session, fields, log),
                view="keepaway",
                boards=fields,
                fsync_simulated=False,
            )
            self.log, self.trainer, self.teaching = wiring.log, wiring.trainer, wiring.teaching
            self.channel, self.departure = wiring.channel, wiring.departure
            self.tamer, self.owners = make_keeper_tamer(cfg, self.agent_sarsa, fields, self.n)
            self.fuse = FusionModule(self.fusion)
            self.feedback = torch.zeros(fields, dtype=torch.int64)  # events learned from, per learner
            self.positive = torch.zeros(fields, dtype=torch.int64)
            # the human effort of each field's episode in progress: events given, cycles the trainer watched
            self.episode_given = torch.zeros(fields, dtype=torch.int64)
            self.episode_watched = torch.zeros(fields, dtype=torch.int64)
            self.effort = torch.zeros(0, len(EFFORT_COLUMNS), dtype=torch.float64)
        self.td: TensorDictBase | None = None
        # the state slot (f * keepers + k) of every field's keepers [B, keepers], for the episode ends
        self._keeper_slots = torch.arange(fields * self.n, device=device).view(fields, self.n)
        self._saved_at: int | None = None
        play = None
        if checkpoint is not None:
            play = self._load(checkpoint["state"])
        # whole cycles compiled, one field per learner: every field runs on its own to its next decision,
        # so each step decides on every field at once (fields of different learners share nothing, so this
        # plays as the lock-step does); with several fields per learner their decisions would all come from
        # the same weights in every step, so they stay in lock-step until any must decide, as elsewhere
        sync = (
            "all"
            if config.kernels == "cycle" and not self.person and int(a.fields_per_learner) == 1
            else "any"
        )
        env = KeepawayEnv(
            fields,
            config,
            device=device,
            seed=component_seed(cfg.seed, "env", self.resumes),
            sync=sync,
            cycle_by_cycle=self.teaching is not None,  # the page is shown every cycle
        )
        self.sim, self.sim_env = env.sim, env
        self.reward_fusion = self._reward_fusion() if self.taught else None
        self.env = env if not self.taught else TransformedEnv(env, self.reward_fusion)
        if play is not None:
            self._load_play(play)
        self.watcher: KeepawayWatcher | None = None
        if self.teaching is not None:
            weight = lambda: float(self.fusion.weight()[0])  # noqa: E731
            budget_s = float(a.hours) * 3600 if float(a.hours) > 0 else None
            self.watcher = KeepawayWatcher(
                self.trainer,
                self.records,
                config,
                weight,
                int(a.log_episodes),
                budget_s=budget_s,
                budget_episodes=int(a.episodes),
            )
            self.watcher.attach(self.sim)
        self.budget_cycles = round(float(a.hours) * CYCLES_PER_HOUR)
        # read once: the loop consults them at every step, and each config lookup costs microseconds
        self.budget_episodes, self.log_episodes = int(a.episodes), int(a.log_episodes)
        self.window = max(1, round(float(a.log_minutes) * CYCLES_PER_MINUTE))
        self.every = max(1, round(float(a.checkpoint_minutes) * CYCLES_PER_MINUTE))
        self.unit = "sim s" if self.budget_cycles > 0 else "episode"  # type: ignore[misc]

    def _reward_fusion(self) -> FeedbackFusion:
        """The env's reward-level fusion: each keeper's reward with H^ of its own previous decision."""
        return FeedbackFusion(
            self.fusion,
            agent_key=keys.KEEPER,
            agents=self.n,
            deciding_key=keys.DECIDING,
            agent_rewards_key=keys.EPISODE_END_REWARDS,
        )

    # --------------------------------------------------------------- the budget

    @property
    def total(self) -> float:
        return (
            round(float(self.cfg.agent.hours) * 3600)
            if self.budget_cycles > 0
            else int(self.cfg.agent.episodes)
        )

    @property
    def position(self) -> float:
        if self.budget_cycles > 0:
            return int(self.records.learner_clock.min()) // CYCLES_PER_SECOND
        return int(self.records.episodes.min())

    @property
    def done(self) -> bool:
        rec, episodes = self.records, self.budget_episodes
        by_time = self.budget_cycles > 0 and bool((rec.learner_clock >= self.budget_cycles).all())
        by_episodes = episodes > 0 and bool((rec.episodes >= episodes).all())
        return by_time or by_episodes

    @property
    def description(self) -> str:
        a = self.cfg.agent
        teams = f"{a.learners} learners x {a.fields_per_learner} fields"
        return f"Sarsa keepers {self.config.keepers}v{self.config.takers}, {teams}"

    # ----------------------------------------------------------------- the loop

    def start(self, logger: Logger) -> None:
        a = self.cfg.agent
        if not self.resumed:
            logger.text(
                "axes",
                "by_hours/*: step = simulated seconds per learner (its fields' experience summed); "
                "by_episodes/* (run by_episodes): step = episodes per learner. Every point: mean over "
                f"{a.learners} learners ({a.fields_per_learner} fields each) of each learner's mean episode "
                "duration, with its 95 % interval.",
            )
            if self.taught:
                logger.text(
                    "trainer",
                    f"{self.who}; fusion={self.cfg.fusion.name}, credit={self.cfg.human.credit}, "
                    f"H^ per {self.cfg.human.model}",
                )
        if self.teaching is not None:
            wait_for_teacher(self.cfg, self.teaching)
        if self.td is None:  # a new run, or one resumed from a checkpoint without its play in progress
            self.td = self.env.reset()
            self.reward = torch.zeros(
                self.fields, device=self.env.device
            )  # of the step that led to each decision
            self.action = torch.zeros(self.fields, dtype=torch.int64, device=self.env.device)
            self.records.advance(self.td[keys.EPISODE_CYCLES])
            if self.taught:
                self.trainer.new_episodes(torch.ones(self.fields, dtype=torch.bool))
        if self._saved_at is None:
            self._saved_at = int(self.records.learner_clock.min())
        self._start_wall, self._start_clock = time.perf_counter(), int(self.records.clock.sum())

    @property
    def who(self) -> str:
        t = self.cfg.trainer
        if self.person:
            return taught_by_person("field 0")
        if t.name == "replay":
            return f"replay: the events of {t.log}, given again on each field's clock"
        return (
            f"simulated:keepaway_oracle: a SIMULATED trainer (Griffith et al.'s oracle against the "
            f"{t.reference or 'hand'} keepers, L={t.frequency}, C={t.consistency}), not a person"
        )

    def advance(self) -> list[Point]:
        points: list[Point] = []
        for _ in range(STEPS_PER_CHUNK):
            if self.done or self.ending:
                break  # (the browser trainer's run is finishing or stopping: the chunk ends now)
            self.step()
            points += self._close_points()
            if points:
                break
        return points

    @property
    def clock(self) -> torch.Tensor:
        """Each field's simulated clock, seconds [B]."""
        return self.records.clock.double() / CYCLES_PER_SECOND

    def step(self) -> None:
        """One env step of every field: the deciding keepers choose and learn, the env runs on."""
        td, n, agent = self.td, self.n, self.agent_sarsa
        rows = td.get(keys.DECIDING).nonzero().squeeze(-1)
        if rows.numel():
            keeper, obs, mask = td.get(keys.KEEPER), td.get(keys.OBSERVATION), td.get(keys.ACTION_MASK)
            every = rows.numel() == self.fields  # (one field per learner: every step, nothing to pick)
            if not every:
                keeper, obs, mask = keeper[rows], obs[rows], mask[rows]
            slots = rows * n + keeper
            if not self.taught:
                chosen = agent.decide(slots, obs, mask, self.reward if every else self.reward[rows])
            else:
                chosen = self._fused_decision(td, rows, keeper, slots, obs, mask)
            self.records.decided(rows, keeper, chosen)
            self.action = chosen if every else self.action.index_put((rows,), chosen)
        td.set(keys.ACTION, self.action)
        td, td_next = self.env.step_and_maybe_reset(td)
        if self.watcher is not None:
            self.watcher(td)
        after = td.get("next")
        ended = after.get(keys.DONE).view(-1)
        cycles = after.get(keys.EPISODE_CYCLES)
        self.reward = after.get(keys.REWARD).view(-1).masked_fill(ended, 0.0)  # a restarted keeper starts
        self.records.advance(cycles)
        if self.taught:
            self._deliver(after)
            self.episode_watched += self.present.to(torch.int64) * after[keys.STEP_CYCLES].view(-1).cpu()
        if bool(ended.any()):
            done_rows = ended.nonzero().squeeze(-1)
            slots = self._keeper_slots[done_rows].view(-1)
            end_rewards = after.get(keys.EPISODE_END_REWARDS)[done_rows].view(-1)
            if self.taught:
                lasted = cycles.view(-1).double().cpu() / CYCLES_PER_SECOND
                taught = self.episode_given > 0
                self._book_effort(ended.cpu())
                self.fusion.end_episode(ended.cpu(), lasted, taught)
                self.trainer.new_episodes(ended.cpu())
            agent.end_episode(slots, end_rewards)
            self.records.finish(ended, cycles)
        self.td = td_next
        self.records.advance(td_next.get(keys.EPISODE_CYCLES))

    @property
    def present(self) -> torch.Tensor:
        """Bool [B]: the fields whose trainer is still there (``trainer.leave_after``)."""
        rec = self.records
        return self.departure.present(rec.episodes, rec.learner_clock.double() / CYCLES_PER_SECOND)

    def _book_effort(self, ended: torch.Tensor) -> None:
        """One effort row per field whose episode ended: its events, the trainer's seconds, its weight."""
        rows = ended.nonzero().flatten()
        effort = torch.stack(
            [
                rows.double(),
                self.records.episodes[rows].double(),
                self.episode_given[rows].double(),
                self.episode_watched[rows].double() / CYCLES_PER_SECOND,
                self.fusion.weight()[rows],
            ],
            dim=1,
        )
        self.effort = torch.cat([self.effort, effort])
        self.episode_given[rows] = 0
        self.episode_watched[rows] = 0

    def _fused_decision(
        self,
        td: TensorDictBase,
        rows: torch.Tensor,
        keeper: torch.Tensor,
        slots: torch.Tensor,
        obs: torch.Tensor,
        mask: torch.Tensor,
    ) -> torch.Tensor:
        """The deciding keepers choose by the fused values; H^ remembers the decisions; the trainer judges."""
        agent = self.agent_sarsa
        tiles, q = agent.action_values(slots, obs)
        owners = self.owners[slots.cpu()].to(self.tamer.model.weight.device)
        h = self.tamer.values(owners, tiles).to(torch.float64)
        decisions = TensorDict(
            {keys.ENV_VALUES: q, keys.HUMAN_VALUES: h, keys.ACTION_MASK: mask, keys.LEARNER: rows.cpu()},
            batch_size=[rows.shape[0]],
        )
        fused = self.fuse(decisions).get(keys.FUSED_VALUES)
        chosen = agent.decide(
            slots,
            obs,
            mask,
            self.reward[rows],
            values=(tiles, q),
            choose_by=fused,
            explore=self.fusion.explores,
        )
        if self.watcher is not None:
            watched = (rows == self.watcher.field).nonzero().view(-1)
            if watched.numel():
                i = watched[:1]
                alone = changed_by_teaching(
                    q[i].cpu(), chosen.view(-1)[i].cpu(), mask[i].cpu(), fused[i].cpu()
                )
                self.watcher.deciding(int(alone))
        estimate = td.get(keys.HUMAN_REWARD_ESTIMATE).clone()
        estimate[rows] = h.gather(1, chosen.cpu().view(-1, 1)).to(estimate)
        td.set(keys.HUMAN_REWARD_ESTIMATE, estimate)
        b, f = self.fields, rows.cpu()
        deciding = torch.zeros(b, dtype=torch.bool)
        deciding[f] = True
        tiles_taken = torch.zeros(b, agent.chosen_tiles.shape[-1], dtype=torch.int64)
        tiles_taken[f] = agent.chosen_tiles.cpu()
        owner = torch.zeros(b, dtype=torch.int64)
        owner[f] = self.owners[slots.cpu()]
        self.tamer.record(deciding, owner, tiles_taken, self.clock)
        full_obs = torch.zeros(b, obs.shape[-1], dtype=obs.dtype)
        full_obs[f] = obs.cpu()
        full_action = torch.zeros(b, dtype=torch.int64)
        full_action[f] = chosen.cpu()
        full_keeper = torch.zeros(b, dtype=torch.int64)
        full_keeper[f] = keeper.cpu()
        judged = deciding & self.present
        values, times = self.trainer.give(full_obs, full_action, judged, self.clock, full_keeper)
        self.episode_given += (values != 0).to(torch.int64)
        self.channel.put(values, times, self.trainer.source)
        return chosen

    def _deliver(self, after: TensorDictBase) -> None:
        """The feedback due on each field's clock into the step's tensordict; H^ learns from it."""
        clock = self.clock
        self.episode_given += self.channel.collect(self.trainer, clock)  # a person's presses, a replay's
        while True:
            fb = self.channel.deliver(clock)
            given = fb[keys.FEEDBACK_MASK]
            if not bool(given.any()):
                break
            after.update(fb)
            self.tamer.learn(fb)
            self.feedback += given.sum(-1)
            self.positive += (given & (fb[keys.FEEDBACK] > 0)).sum(-1)

    # --------------------------------------------------------------- the curves

    def _close_points(self) -> list[Point]:
        rec, every = self.records, self.log_episodes
        points = []
        slowest = int(rec.learner_clock.min())
        while slowest >= (self.time_windows + 1) * self.window:
            stats = rec.time_window(self.time_windows * self.window, (self.time_windows + 1) * self.window)
            self.time_windows += 1
            if stats is None:  # no episode ended in this window on any field
                continue
            wall = time.perf_counter() - self._start_wall
            stats["field_cycles_per_s"] = (int(rec.clock.sum()) - self._start_clock) / max(wall, 1e-9)
            for k in range(rec.keepers):
                stats[f"decisions_total_keeper{k}"] = float(rec.table[:, 5 + k].sum()) / rec.learners
            stats.update(self.feedback_stats())
            end = self.time_windows * self.window
            record = {
                "axis": "hours",
                "hours": end / CYCLES_PER_HOUR,
                "sim_seconds": end // CYCLES_PER_SECOND,
                **stats,
            }
            points.append(Point(record, end // CYCLES_PER_SECOND, prefix="by_hours/"))
        while int(rec.episodes.min()) >= (self.episode_windows + 1) * every:
            lo = self.episode_windows * every
            stats = rec.episode_window(lo, lo + every)
            stats.update(self.feedback_stats())
            self.episode_windows += 1
            record = {"axis": "episodes", "episode": lo + every, **stats}
            points.append(Point(record, lo + every, axis="by_episodes", prefix="by_episodes/"))
        return points

    def points_of(self, history: list[dict[str, Any]]) -> list[Point]:
        out = []
        for r in history:
            if r.get("axis") == "hours":
                out.append(Point(r, int(r["sim_seconds"])))
            elif r.get("axis") == "episodes":
                out.append(Point(r, int(r["episode"]), axis="by_episodes"))
        return out

    def feedback_stats(self) -> dict[str, float]:
        """The weight, R's spread and the feedback so far, per learner (with a trainer)."""
        if not self.taught:
            return {}
        watched = self.effort[:, 3].sum() + self.episode_watched.sum() / CYCLES_PER_SECOND
        return {
            **self.fusion.stats(),
            "feedback/events_per_learner": float(self.feedback.double().mean()),
            "feedback/trainer_minutes_per_learner": float(watched) / 60.0 / self.fields,
            "feedback/trainer_present_share": float(self.present.double().mean()),
            "feedback/positive_share": float(self.positive.sum() / self.feedback.sum().clamp(min=1)),
            "feedback/credited_share": self.tamer.credited_share,
        }

    def postfix(self, point: Point) -> dict[str, str]:
        r = point.record
        return {"episode_s": f"{r['episode_s_mean']:.2f}", "hold": f"{r['hold_share']:.2f}"}

    def save_due(self) -> bool:
        slowest = int(self.records.learner_clock.min())
        if slowest - self._saved_at >= self.every:
            self._saved_at = slowest
            return True
        return False

    # ---------------------------------------------------------------- checkpoints

    def checkpoint(self) -> dict[str, Any]:
        a, agent = self.cfg.agent, self.agent_sarsa
        state: dict[str, Any] = {
            "agent": agent.state_dict(),
            "records": self.records.state_dict(),
            "resumes": self.resumes,
            "time_windows": self.time_windows,
            "episode_windows": self.episode_windows,
            "play": self._play_state(),
        }
        human = None
        if self.taught:
            state["human"] = {
                "human_weight": self.tamer.model.weight.clone(),
                "fusion": self.fusion.state_dict(),
                "trainer": self.trainer.state_dict(),
                "feedback": self.feedback.clone(),
                "positive": self.positive.clone(),
                "tamer_counts": [self.tamer.decisions, self.tamer.credited],
                "effort": self.effort.clone(),
                "effort_columns": list(EFFORT_COLUMNS),
            }
            human = {
                "scheme": self.cfg.fusion.name,
                "model": str(self.cfg.human.model),
                "scaling": self.fusion.scaling,
                "q_spread": self.fusion.q_spread.tolist(),
                "weight": self.fusion.weight().tolist(),
            }
        policy = export_policy(  # its weight tables are the state's (state -> agent -> weight)
            "tile_sarsa",
            tile_widths=agent.coder.widths.tolist(),
            tilings=agent.coder.tilings,
            size=agent.coder.size,
            num_actions=agent.coder.num_actions,
            learners="(field // fields_per_learner) * keepers + keeper",
            fields_per_learner=a.fields_per_learner,
            teams=int(a.learners),
            share_weights=bool(a.share_weights),
            human=human,
        )
        return {"state": state, "policy": policy, "domain_config": asdict(self.config)}

    def _play_state(self) -> dict[str, Any]:
        """Everything in flight: the env's fields, the loop's step, and with a trainer H^'s credit windows,
        the channel's waiting events, the episodes' effort and the last event learned from."""
        play: dict[str, Any] = {
            "env": self.sim_env.state_dict(),
            "td": self.td.cpu().to_dict(),
            "reward": self.reward.clone().cpu(),
            "action": self.action.clone().cpu(),
            "saved_at": self._saved_at,
        }
        if self.taught:
            play.update(
                reward_fusion=self.reward_fusion.get_extra_state(),
                tamer=self.tamer.state_dict(),
                channel=self.channel.state_dict(),
                episode_given=self.episode_given.clone(),
                episode_watched=self.episode_watched.clone(),
                log_seq=self.log.last_seq,  # the last event of each session the learner has been given
            )
        return play

    def _load_play(self, play: dict[str, Any]) -> None:
        """Continue the play of :meth:`_play_state` exactly where the checkpoint left it."""
        try:
            self.sim_env.load_state_dict(play["env"])
            device = self.env.device
            self.td = TensorDict(play["td"], batch_size=[self.fields]).to(device)
            self.reward = play["reward"].to(device).clone()
            self.action = play["action"].to(device=device, dtype=torch.int64).clone()
            self._saved_at = int(play["saved_at"])
            if self.taught:
                self.reward_fusion.set_extra_state(play["reward_fusion"])
                self.tamer.load_state_dict(play["tamer"])
                self.channel.load_state_dict(play["channel"])
                self.episode_given.copy_(play["episode_given"])
                self.episode_watched.copy_(play["episode_watched"])
                # exactly once: a simulated trainer or a replay gives the events after the checkpoint again
                # (matched in the log, not written twice); a person's presses logged after it are learned now
                unseen = self.log.resume(play["log_seq"], regenerated=not self.person)
                self.channel.put_board(0, unseen)
                self.episode_given[0] += sum(ev.value != 0 for ev in unseen)
        except (KeyError, TypeError, RuntimeError, ValueError, AttributeError) as e:
            raise CheckpointError(
                f"checkpoint of {self.run_dir} does not continue this keepaway run's play ({e!r})"
            ) from None

    def _load(self, state: dict[str, Any]) -> dict[str, Any] | None:
        """Restore what every checkpoint holds; returns the play in progress (None: an older checkpoint,
        whose episodes in progress are abandoned)."""
        try:
            play = state.get("play")
            self.agent_sarsa.load_state_dict(state["agent"])
            if play is None:
                warnings.warn(
                    f"checkpoint of {self.run_dir} predates saved episodes in progress: they are abandoned "
                    "and the fields restart on a new seed, so this run will not match an uninterrupted one",
                    CheckpointWarning,
                    stacklevel=2,
                )
                self.agent_sarsa.forget_episodes()
            self.records.load_state_dict(state["records"])
            self.resumes = int(state["resumes"]) + 1
            self.time_windows, self.episode_windows = (
                int(state["time_windows"]),
                int(state["episode_windows"]),
            )
            if self.taught:
                human = state["human"]
                self.tamer.model.weight.copy_(human["human_weight"])
                self.fusion.load_state_dict(human["fusion"])
                self.trainer.load_state_dict(human["trainer"])
                self.feedback.copy_(human["feedback"])
                self.positive.copy_(human["positive"])
                self.tamer.decisions, self.tamer.credited = (int(x) for x in human["tamer_counts"])
                self.effort = human["effort"].to(torch.float64).clone()
        except (KeyError, TypeError, RuntimeError, ValueError) as e:
            raise CheckpointError(
                f"checkpoint of {self.run_dir} is not this keepaway run's ({e!r})"
            ) from None
        return play

    # ------------------------------------------------------------------- results

    def final(self) -> dict[str, Any]:
        axis = "hours" if self.budget_cycles > 0 else "episodes"  # the curve of the budget's axis
        points = [h for h in self.history if h.get("axis") == axis]
        rec = self.records
        if points:
            final = dict(points[-1])
        elif rec.table.shape[0]:  # a run shorter than one point of its curve: all its episodes
            final = {"axis": axis, "episode": int(rec.episodes.min()), **rec.summary(rec.table)}
        else:
            return {}
        final["hours"] = int(rec.learner_clock.min()) / CYCLES_PER_HOUR
        if self.taught:
            final["feedback_events"] = float(self.feedback.sum())
            final.update(self.feedback_stats())
        return final

    def report(self, final: dict[str, Any]) -> list[str]:
        a = self.cfg.agent
        low, high = final["episode_s_ci95_low"], final["episode_s_ci95_high"]
        if final["axis"] == "hours" and "sim_seconds" in final:
            window = f"last {a.log_minutes:g} simulated minutes"
        elif "episode" in final and final["episode"] > a.log_episodes:
            window = f"episodes {final['episode'] - a.log_episodes + 1}-{final['episode']}"
        else:
            window = "all its episodes"
        lines = [
            f"Done: after {final['hours']:.2f} simulated hours per learner ({a.learners} learners), "
            f"episodes last {final['episode_s_mean']:.2f} s (95% CI {low:.2f}..{high:.2f}; {window}, "
            f"{'exploring' if not self.taught or self.fusion.explores else 'greedy'})"
        ]
        if self.taught:
            who = TRAINER_LABELS.get(self.cfg.trainer.name, self.cfg.trainer.name)
            lines.append(
                f"Feedback:         {final['feedback_events']:.0f} events of the {who} "
                f"(fusion={self.cfg.fusion.name}, mean weight on H^ "
                f"{final.get('fusion/weight_mean', 0.0):.2f})"
            )
            lines.append(f"Feedback log:     {self.log.path}")
        return lines

    def score(self, final: dict[str, Any]) -> float | None:
        return final.get("episode_s_mean")

    def hparam_metrics(self, final: dict[str, Any]) -> dict[str, float]:
        return {"hparam/episode_s_last": final["episode_s_mean"]}

    def close(self) -> None:
        a = self.cfg.agent
        budget = (
            ("agent.hours", 2 * float(a.hours)) if float(a.hours) > 0 else ("agent.episodes", 2 * a.episodes)
        )
        self.end_teaching(*budget)
        if self.log is not None:
            self.log.close()
