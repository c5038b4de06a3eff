"""The cross-entropy method on Tetris, alone or taught by a trainer (thesis Figures 3.6 and 4.1).

``train.py agent=cem`` (``trainer=none``): each iteration samples a population of linear afterstate values,
plays their games in compiled code, refits the Gaussian to the elite, then tests the mean weights on fresh
games (the curve).

With a trainer (``fusion=<scheme> trainer=<t>``, the combined learner), one iteration is one episode of the
fusion, in four parts:

1. **Watch.** The fused mean policy plays one game (at most ``agent.watch_pieces`` placements) on a
   ``TetrisEnv`` wrapped in ``FeedbackFusion``: at each placement the feedback due on the simulated clock
   comes out of the channel into the tensordict and H^ (TAMER) learns from it; R (the CE value) and H^ of
   every placement go through the fusion component, which chooses; the trainer judges the placement and its
   events go into the channel and the feedback log. One trainer watches one board, as a person would.
2. **CE step.** Every candidate plays its games acting on its own R fused with H^ by the same component (its
   compiled twin), so the elite are the weights that work best together with what the trainer taught; by
   default only while the trainer teaches and the weight rests on evidence, on R alone otherwise
   (``agent.rank_candidates``).
3. **Test.** The fused mean policy plays ``agent.eval_games`` fresh games: their lines are the learning
   curve, and their placements' match count is the m of the trust factor.
4. **Weight.** The fusion ends its episode: eq. 4.4 folds in (lines, m) for the trust factor; the annealed
   weight decays by its factor; a fixed weight stays.

Every random draw of iteration t (CE, games, trainer, control-sharing coins) is seeded from (seed, t) or
restored from the checkpoint, so a resumed run continues as if never stopped. Feedback events are appended
to ``feedback.jsonl`` as they are given, so a crash loses none of them, and each checkpoint names the last
event its learner was given: a resumed run neither logs an event twice nor loses one (``FeedbackLog.resume``).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv

from hfrl_torch import keys
from hfrl_torch.agents.cem import CrossEntropyMethod
from hfrl_torch.agents.cem.fused_rollout import FusedRollout
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.common.logger import Logger
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.tetris.env import TetrisEnv
from hfrl_torch.envs.tetris.features import feature_id, feature_names
from hfrl_torch.experiment.checks import candidate_ranking, check_cem
from hfrl_torch.experiment.factories import (
    make_cem_config,
    make_feedback_wiring,
    make_fusion,
    make_rollout,
    make_rules,
    make_tamer,
    make_trainer,
    warm_up,
)
from hfrl_torch.experiment.learners.tetris_games import TRAINER_LABELS
from hfrl_torch.experiment.run import Learner, Point
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.fusion import changed_by_teaching
from hfrl_torch.fusion.transform import FeedbackFusion, FusionModule
from hfrl_torch.interactive.live import LiveTeaching
from hfrl_torch.interactive.tetris_live import SLOW_REACTION_S, BrowserTetrisTrainer, TetrisPage


class CEMLearner(Learner):
    """Noisy CE over the weights of a linear afterstate value, with or without a trainer."""

    agent = "cem"
    unit = "it"
    weight_evidence = frozenset({"compared", "searched"})

    @classmethod
    def check(cls, cfg: DictConfig) -> None:
        check_cem(cfg)

    x_key = "iteration"

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        super().__init__(cfg, run_dir, checkpoint)
        self.rules = make_rules(cfg)
        self.names = feature_names(feature_id(cfg.domain.features), self.rules.width)
        self.taught = cfg.trainer.name != "none"
        self.ranking = candidate_ranking(cfg)
        self.teaching: LiveTeaching | None = None
        self.page: TetrisPage | None = None
        self.log: FeedbackLog | None = None
        n = len(self.names)
        mean = scale = None
        self.searches_weight = False
        if self.taught:
            self._build_feedback(cfg, run_dir)
            self.searches_weight = self.fusion.searches_weight
            rollout = FusedRollout(
                self.rules,
                cfg.domain.features,
                cfg.human.features,
                self.fusion,
                cfg.domain.max_pieces,
                searches_weight=self.searches_weight,
            )
            if self.searches_weight:  # the weight on H^ is one more dimension of the search, on its own scale
                ce = make_cem_config(cfg)
                mean = torch.cat([torch.full((n,), ce.initial_mean), self.fusion.weight()[:1]])
                std = float(cfg.fusion.adaptive.search_std) / math.sqrt(ce.initial_variance)
                scale = torch.cat([torch.ones(n), torch.tensor([std])])
                n += 1
        else:
            rollout = make_rollout(cfg)
        self.rollout = rollout
        self.cem = CrossEntropyMethod(n, make_cem_config(cfg), rollout, seed=cfg.seed, mean=mean, scale=scale)
        if checkpoint is not None:
            self._load(checkpoint["state"])

    def _build_feedback(self, cfg: DictConfig, run_dir: Path) -> None:
        h = cfg.human
        self.fusion = make_fusion(cfg, type(self), 1)
        self.human_names = feature_names(feature_id(h.features), self.rules.width)
        self.human = make_tamer(cfg, 1, len(self.human_names))
        self.clock = 0.0
        self.seconds_per_placement = float(h.seconds_per_placement)
        wiring = make_feedback_wiring(
            cfg, run_dir, self.fusion, lambda log: make_trainer(cfg, log), BrowserTetrisTrainer, boards=1
        )
        self.log, self.trainer, self.teaching = wiring.log, wiring.trainer, wiring.teaching
        self.channel, self.departure = wiring.channel, wiring.departure
        if self.teaching is not None:
            self.page = TetrisPage(self.teaching.session, int(cfg.agent.iterations))
            self.who = "a person in the browser (human:browser)"
        else:
            source = (
                self.trainer.source if self.trainer.source != "trainer" else f"simulated:{cfg.trainer.name}"
            )
            self.who = f"{source} (trainer={cfg.trainer.name}; a simulated or replayed trainer, not a person)"
        self.watched = TransformedEnv(
            TetrisEnv(batch=1, rules=self.rules, features=h.features, max_pieces=cfg.agent.watch_pieces),
            FeedbackFusion(self.fusion),
        )
        self.choose = FusionModule(self.fusion, select="greedy", count=False)

    @property
    def value_weights(self) -> torch.Tensor:
        """The mean policy's value weights (without the searched weight on H^)."""
        return self.cem.mean[: len(self.names)]

    @property
    def total(self) -> float:
        return int(self.cfg.agent.iterations)

    @property
    def position(self) -> float:
        return self.cem.iteration

    @property
    def description(self) -> str:
        scheme = f"+{self.cfg.fusion.name}" if self.taught else ""
        return f"CE{scheme} {self.rules.width}x{self.rules.height}"

    def start(self, logger: Logger) -> None:
        warm_up(self.cfg)
        if not self.resumed:
            r = self.rules
            logger.text(
                "rules", f"{r.describe()}, board {r.width}x{r.height}, features {self.cfg.domain.features}"
            )
            if self.taught:
                logger.text("trainer", f"{self.who}, fusion={self.cfg.fusion.name}")
        if self.teaching is not None:  # only a new run waits for the page
            first = not self.resumed and self.cem.iteration == 0
            wait = float(self.cfg.trainer.wait_for_page_s) if first else 0.0
            self.teaching.announce(wait, "learning from the game alone")

    # -------------------------------------------------------------------- iterate

    def advance(self) -> list[Point]:
        t = self.cem.iteration
        t0 = time.perf_counter()
        metrics: dict[str, float] = {}
        if self.taught:
            weight = float(self.fusion.weight()[0])  # 0 for none and human_only
            self.fusion.generator.manual_seed(component_seed(self.cfg.seed, "cem_fusion", t))
            watched = dict.fromkeys(("env_return", "fused_return", "placements", "given", "positive"), 0.0)
            present = self.departure.present_one(t, self.clock)
            if present:  # the trainer's game
                watched = self.watch_game(component_seed(self.cfg.seed, "watched_game", t), t)
            fused_now = present and self.fusion.weight_informed()
            if self.ranking == "alone" or (self.ranking == "fused_while_teaching" and not fused_now):
                self.rollout.weight = 0.0  # the candidates on R alone: R goes on improving past H^
            if self.teaching is not None:  # the browser trainer: Ctrl-C ends the person's game and the chunk
                if self.teaching.session.ending == "stopping":
                    return []  # the game's presses are learned and in the log; resumed, the round is redone
                self.page.practising(t)
            self.rollout.human_weights = self.human.model.weight[0].detach().clone()
        metrics.update(self.cem.step())
        if self.taught:
            self.rollout.weight = None
        searched = compared = None
        if self.searches_weight:
            searched = self.cem.mean[-1:].clone()
            metrics["fusion/search_std"] = float(self.cem.variance[-1].sqrt())
        if self.taught and self.fusion.compared_weights() is not None:
            eval_lines, compared = self.compare_weights(metrics)
        else:
            eval_lines = self.cem.evaluate_mean()
        ev = summarize(eval_lines, floor=0.0)
        elapsed = time.perf_counter() - t0
        metrics.update(
            {
                "eval/mean_policy_lines_mean": ev["mean"],
                "eval/mean_policy_lines_median": ev["median"],
                "eval/mean_policy_lines_ci95_low": ev["ci95_low"],
                "eval/mean_policy_lines_ci95_high": ev["ci95_high"],
                "eval/capped_games": self.cem.last_eval_capped,
            }
        )
        if self.taught:
            games = self.rollout.last
            self.fusion.count_matches(torch.zeros_like(games.matches), games.matches, games.compared)
            m = float(self.fusion.matches.rates()[0])
            self.fusion.end_episode(
                performance=ev["mean"],
                taught=torch.tensor([watched["given"] > 0]),
                compared=compared,
                searched=searched,
            )
            if compared is not None:
                metrics["fusion/paired_next_weight"] = float(self.fusion.weight()[0])
            metrics.update(
                {
                    "episode/env_return": watched["env_return"],
                    "episode/fused_return": watched["fused_return"],
                    "episode/placements": watched["placements"],
                    "feedback/given": watched["given"],
                    "feedback/positive_share": watched["positive"] / watched["given"]
                    if watched["given"]
                    else 0.0,
                    "feedback/trainer_present": float(watched["given"] > 0),
                    "feedback/trainer_minutes": watched["placements"] * self.seconds_per_placement / 60.0,
                    "feedback/learned_total": float(self.human.applied.sum()),
                    "fusion/weight": weight,
                    "fusion/weight_next": float(self.fusion.weight()[0]),
                    "fusion/match_rate": m,
                    "time/iteration_s": elapsed,
                }
            )
            if self.page is not None:
                self.page.point(t, ev["mean"], taught=watched["placements"] > 0)
        else:
            placements = metrics["population/placements"] + self.cem.last_eval_pieces
            metrics.update(
                {"time/placements_per_s": placements / max(elapsed, 1e-9), "time/iteration_s": elapsed}
            )
        step = self.cem.iteration
        return [Point({"iteration": step, **metrics}, step)]

    def compare_weights(self, metrics: dict[str, float]) -> tuple[torch.Tensor, torch.Tensor]:
        """``fusion.weight=adaptive``: the mean policy's test games at every weight the fusion compares, on
        the same games (the next iteration plays at the best). Returns the lines at this iteration's weight
        (the curve; its games also give the match count) and the comparison [1, K, G] for ``end_episode``."""
        arms = self.fusion.compared_weights()
        now = int((arms - self.fusion.weight()[0]).abs().argmin())
        lines, games = [], None
        for k, w in enumerate(arms.tolist()):
            self.rollout.weight = w
            lines.append(self.cem.evaluate_mean())
            if k == now:
                games, capped = self.rollout.last, self.cem.last_eval_capped
                pieces = self.cem.last_eval_pieces
        self.rollout.weight = None
        self.rollout.last, self.cem.last_eval_capped, self.cem.last_eval_pieces = games, capped, pieces
        table = torch.stack(lines).to(torch.float64)
        for w, row in zip(arms.tolist(), table, strict=True):
            metrics[f"fusion/paired_lines_w{w:g}"] = float(row.mean())
        return lines[now], table.unsqueeze(0)

    def watch_game(self, game_seed: int, episode: int) -> dict[str, float]:
        """The trainer watches the fused mean policy play one game; H^ learns from every event; its totals.

        The game's last events, which arrive after its last placement, are learned too (they credit its last
        placements). With a person in the browser the game runs on the wall clock at the page's speed, every
        placement is shown on the page (``TetrisPage``: presses are filed under the placement on screen
        0.3 s before them), and the game stops early if the person leaves or the run is ending.
        """
        env, live = self.watched, self.teaching.session if self.teaching is not None else None
        if self.page is not None and live is not None and live.teaching():
            self.page.start_game(episode)
        n_env = len(self.names)
        env.set_seed(game_seed)  # a TransformedEnv passes no reset_game_seed down: seed the env's own draw
        td = env.reset()
        totals = {"env_return": 0.0, "fused_return": 0.0, "placements": 0.0, "given": 0.0, "positive": 0.0}
        now = self.clock
        episode_t = torch.tensor([episode])
        while True:
            if live is not None:
                if not live.teaching() or live.ending is not None:
                    break
                now = live.wait_turn()
            self._learn_due(td, now)
            feats = td[keys.AFTERSTATE_FEATURES][..., :n_env].to(torch.float64)
            td.set(keys.ENV_VALUES, (feats * self.value_weights).sum(-1))
            td.set(keys.HUMAN_VALUES, self.human.model(placement_deltas(td)))
            action = self.choose(td).get(keys.ACTION)
            alone = None
            if self.page is not None:
                best = int(changed_by_teaching(td[keys.ENV_VALUES][:1], action, td[keys.ACTION_MASK][:1]))
                alone = None if best < 0 else best
            events = self.trainer.give(td, action, now, episode_t)
            self.human.record(td, action, now)
            self.channel.put_events(events)
            self._count(totals, events)
            td.set(
                keys.HUMAN_REWARD_ESTIMATE,
                td[keys.HUMAN_VALUES].gather(1, action.view(1, 1)).to(torch.float32),
            )
            td = env.step(td)
            nxt = td["next"]
            if self.page is not None:
                weight = float(td[keys.FUSION_WEIGHT].reshape(-1)[0])
                self.page.placed(td, episode, now, weight=weight, alone=alone)
            totals["env_return"] += float(nxt[keys.ENV_REWARD].sum())
            totals["fused_return"] += float(nxt[keys.REWARD].sum())
            totals["placements"] += 1
            now += float(self.cfg.human.seconds_per_placement)
            if bool(nxt[keys.DONE].any()):
                self.trainer.end_games(nxt[keys.DONE].view(-1), nxt[keys.LINES].view(-1))
                break
            td = td["next"]
        if live is not None and totals["placements"] > 0:  # feedback on the last placements is on its way
            live.sleep(self.teaching.session.reaction_s + SLOW_REACTION_S)  # (cut short when the run ends)
            late = self.teaching.trainer.late(live.clock())
            self.channel.put_events(late)
            self._count(totals, late)
        while self.channel.pending:
            self.human.learn(self.channel.deliver(math.inf))
        self.clock = now
        return totals

    def _learn_due(self, td: TensorDictBase, now: float) -> None:
        td.update(self.channel.deliver(now))
        self.human.learn(td)

    @staticmethod
    def _count(totals: dict[str, float], events: list[list[Any]]) -> None:
        totals["given"] += float(sum(len(e) for e in events))
        totals["positive"] += float(sum(ev.value > 0 for e in events for ev in e))

    def postfix(self, point: Point) -> dict[str, str]:
        r = point.record
        out = {"eval_lines": f"{r['eval/mean_policy_lines_mean']:.1f}"}
        if self.taught:
            m = r["fusion/match_rate"]
            out.update(
                w=f"{r['fusion/weight']:.2f}",
                m="-" if math.isnan(m) else f"{m:.2f}",
                fb=f"{r['feedback/given']:.0f}",
            )
        else:
            out.update(pop_lines=f"{r['population/lines_mean']:.1f}", noise=f"{r['cem/noise']:.2f}")
        return out

    # ---------------------------------------------------------------- checkpoints

    def checkpoint(self) -> dict[str, Any]:
        linear: dict[str, Any] = {
            "features": self.cfg.domain.features,
            "feature_names": self.names,
            "weights": self.value_weights.clone(),
        }
        if not self.taught:
            policy = export_policy("linear", **linear)
            return {"state": self.cem.state_dict(), "policy": policy, "rules": self.rules.as_dict()}
        state = {
            "cem": self.cem.state_dict(),
            "human": self.human.learner_state(),
            "fusion": self.fusion.state_dict(),
            "trainer": self.trainer.state_dict(),
            "channel": self.channel.state_dict(),
            "clock": self.clock,
            "log_seq": self.log.last_seq,  # the last event of each session the learner has been given
        }
        policy = export_policy(
            "fused",
            **linear,
            scheme=self.fusion.decision,
            weight=float(self.fusion.weight()[0]),
            normalise=self.fusion.scaling == "decision",
            human_features=self.cfg.human.features,
            human_weights=self.human.model.weight[0].detach().clone(),
        )
        return {"state": state, "policy": policy, "rules": self.rules.as_dict()}

    def _load(self, state: dict[str, Any]) -> None:
        try:
            if not self.taught:
                self.cem.load_state_dict(state)
                return
            self.cem.load_state_dict(state["cem"])
            self.human.load_learner_state(state["human"])
            self.fusion.load_state_dict(state["fusion"])
            self.trainer.load_state_dict(state["trainer"])
            self.channel.load_state_dict(state["channel"])
            self.clock = float(state["clock"])
            # exactly once: a simulated trainer or a replay gives the events after the checkpoint again (not
            # logged twice); a person's logged presses the learner never saw are learned now
            self.channel.put_board(0, self.log.resume(state["log_seq"], regenerated=self.teaching is None))
        except (KeyError, RuntimeError, TypeError, ValueError) as e:
            raise CheckpointError(f"checkpoint of {self.run_dir} is not this CE run's ({e!r})") from None

    # ------------------------------------------------------------------- results

    def report(self, final: dict[str, Any]) -> list[str]:
        low, high = final["eval/mean_policy_lines_ci95_low"], final["eval/mean_policy_lines_ci95_high"]
        lines = [
            f"Done: mean policy {final['eval/mean_policy_lines_mean']:.1f} lines per game "
            f"(95% CI {low:.1f}..{high:.1f})"
        ]
        if self.taught:
            who = TRAINER_LABELS.get(self.cfg.trainer.name, self.cfg.trainer.name)
            lines.append(
                f"Feedback:         {final['feedback_events']:.0f} events of the {who} "
                f"(fusion={self.cfg.fusion.name}, weight on H^ now {final['fusion/weight_next']:.2f})"
            )
            lines.append(f"Feedback log:     {self.log.path}")
        return lines

    def final(self) -> dict[str, Any]:
        final = super().final()
        if final and self.taught:
            final["feedback_events"] = float(sum(r["feedback/given"] for r in self.history))
        return final

    def score(self, final: dict[str, Any]) -> float | None:
        return final.get("eval/mean_policy_lines_mean")

    def hparam_metrics(self, final: dict[str, Any]) -> dict[str, float]:
        return {"hparam/eval_lines_mean": final["eval/mean_policy_lines_mean"]}

    def close(self) -> None:
        self.end_teaching("agent.iterations", 2 * int(self.cfg.agent.iterations))
        if self.log is not None:
            self.log.close()
