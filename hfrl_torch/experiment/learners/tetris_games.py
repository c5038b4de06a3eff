"""L Tetris learners playing games side by side (TAMER, Q-learning, PG): what they share.

One batched ``TetrisEnv`` holds every learner's board (B = learners), so ten seeds are one run. Each
placement is made on every board at once; a board whose game ends restarts at once, and a learner that has
played its ``agent.games`` games stops learning (its board plays on, unjudged and uncounted). The curve has
one point per game number g, written once every learner has played its g-th game: the lines of the
learners' g-th games (mean, median, 95 % interval over learners), plus what each learner adds.

With a trainer, the learners also learn H^ (TAMER) from its feedback: at each placement the events due on
the simulated clock (one placement per ``human.seconds_per_placement``) come out of the feedback channel
into the tensordict, H^ learns from them, the learner chooses (through the one fusion component), and the
trainer's events on that placement go into the channel. One simulated trainer watches each board.
"""

from __future__ import annotations

from abc import abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.agents.policies import export_policy
from hfrl_torch.agents.tamer import TamerAgent
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.common.logger import Logger
from hfrl_torch.common.seeding import component_generator
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.tetris.env import TetrisEnv
from hfrl_torch.envs.tetris.features import feature_id, feature_names, feature_size
from hfrl_torch.experiment.factories import (
    make_env,
    make_feedback_wiring,
    make_fusion,
    make_rollout,
    make_rules,
    make_tamer,
    make_trainer,
)
from hfrl_torch.experiment.run import Learner, Point, WallClockSaves
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.transform import FusionModule

CHUNK_PLACEMENTS = 200  # placements on every board per chunk at most (a chunk also ends at a new point)
# what a decision adds to the step's tensordict (the feedback due, the values fused and chosen by): not the
# env's, so left out of its step, which would carry each entry into the next step's tensordict and through
# every partial reset; each decision starts from the observation alone
DECISION_KEYS = (
    keys.FEEDBACK,
    keys.FEEDBACK_TIME,
    keys.FEEDBACK_MASK,
    keys.FEEDBACK_SOURCE,
    keys.ENV_VALUES,
    keys.HUMAN_VALUES,
    keys.FUSED_VALUES,
    keys.FUSION_WEIGHT,
)
SAVE_EVERY_S = 10.0  # wall seconds between checkpoints


class TetrisGames(Learner):
    """The shared loop of L Tetris learners, one board each (see the module docstring)."""

    unit = "game"
    x_key = "game"
    taught: ClassVar[bool] = False  # learns H^ from a trainer

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        super().__init__(cfg, run_dir, checkpoint)
        a = cfg.agent
        self.learners, self.games = int(a.learners), int(a.games)
        self.rules = make_rules(cfg)
        self.env: TetrisEnv = make_env(cfg, self.learners, features=self.env_features)
        L, G = self.learners, self.games
        self.lines = torch.zeros(L, G, dtype=torch.int64)
        self.pieces = torch.zeros(L, G, dtype=torch.int64)
        self.played = torch.zeros(L, dtype=torch.int64)
        self.given = torch.zeros(
            L, G, 3, dtype=torch.int64
        )  # events given in each game: all, positive, negative
        self.watched = torch.zeros(L, G, dtype=torch.int64)  # placements of each game the trainer watched
        self.placement = 0
        self.closed = 0
        self.rows = torch.arange(L)  # every learner's row, for indexing per-learner tables
        self.log: FeedbackLog | None = None
        if self.taught and cfg.trainer.name != "none":
            h = cfg.human
            self.human: TamerAgent | None = make_tamer(
                cfg, L, feature_size(feature_id(h.features), self.rules.width)
            )
            self.seconds_per_placement = float(h.seconds_per_placement)
        else:
            self.trainer, self.human = None, None
        self.fusion = make_fusion(cfg, type(self), L, option=self.fusion_option)
        if self.human is not None:
            wiring = make_feedback_wiring(
                cfg, run_dir, self.fusion, lambda log: make_trainer(cfg, log), boards=L
            )
            self.log, self.trainer = wiring.log, wiring.trainer
            self.channel, self.departure = wiring.channel, wiring.departure
        self.fuse = FusionModule(self.fusion, select=self.select)
        if checkpoint is None:
            self.td = self.env.reset()
        else:
            self.td = self._load(checkpoint["state"])
        self.saves = WallClockSaves()
        self.logger: Logger | None = None

    # ------------------------------------------------------------------ subclass

    env_features: ClassVar[str] = "bt"
    select: ClassVar[str | None] = None  # "greedy": the fused values' best placement is the action
    fusion_option: ClassVar[str | None] = None  # the learner's own fusion rule (None: the config's)

    @abstractmethod
    def act(self, td: TensorDictBase, active: torch.Tensor) -> torch.Tensor:
        """The placement [L] of every board (after H^ learned from the feedback due, with a trainer)."""

    def observe(self, td: TensorDictBase, active: torch.Tensor) -> None:
        """After the step (``td`` holds its ``"next"``): what the learner learns from it."""

    def game_metrics(self, g: int) -> dict[str, float]:
        """What the learner adds to the point of game g."""
        return {}

    def learner_state(self) -> dict[str, Any]:
        """The learner's own state for a checkpoint."""
        return {}

    def load_learner_state(self, state: dict[str, Any]) -> None:
        """Restore :meth:`learner_state`'s output."""

    def policy(self) -> dict[str, Any]:
        """What ``evaluate.py`` plays (learner 0's linear afterstate policy), written with
        :func:`~hfrl_torch.agents.policies.export_policy` (:meth:`linear_policy` does)."""
        return {}

    # ---------------------------------------------------------------- the loop

    @property
    def total(self) -> float:
        return self.learners * self.games

    @property
    def position(self) -> float:
        return float(self.played.clamp(max=self.games).sum())

    @property
    def description(self) -> str:
        return f"{self.label} {self.rules.width}x{self.rules.height}"

    label: ClassVar[str] = ""

    @property
    def clock(self) -> float:
        """The simulated clock of the next placement (seconds)."""
        return self.placement * self.seconds_per_placement

    def start(self, logger: Logger) -> None:
        self.logger = logger
        if self.resumed:
            return
        logger.text("rules", f"{self.rules.describe()}, board {self.rules.width}x{self.rules.height}")
        if self.trainer is not None:
            logger.text(
                "trainer",
                f"{self.trainer.source} (trainer={self.cfg.trainer.name}; a simulated or replayed trainer, "
                f"not a person), fusion={self.cfg.fusion.name}; one trainer per learner",
            )

    def advance(self) -> list[Point]:
        taught = self.trainer is not None
        active = self.played < self.games
        for _ in range(0 if self.done else CHUNK_PLACEMENTS):
            td = self.td
            if taught:
                self.feedback(td)
            action = self.act(td, active)
            if taught:  # judged; and only a taught learner's decisions write entries
                self.judge(td, action, active)
                td = td.exclude(*DECISION_KEYS)
            td.set(keys.ACTION, action)
            td, self.td = self.env.step_and_maybe_reset(td)
            self.observe(td, active)
            ended = self._book(td.get("next"), active)
            self.placement += 1
            if ended:  # only then can a point close or the budget be spent
                if self.done or int(self.played.min()) > self.closed:  # a game every learner has played
                    break
                active = self.played < self.games
        return self._close_points()

    def feedback(self, td: TensorDictBase) -> None:
        """Before a choice: the channel's due events into ``td``, and H^ learns from them (with none due
        there is nothing to write or learn)."""
        delivery = self.channel.deliver(self.clock)
        if bool(delivery.get(keys.FEEDBACK_MASK).any()):
            td.update(delivery)
            self.human.learn(td)

    def judge(self, td: TensorDictBase, action: torch.Tensor, active: torch.Tensor) -> None:
        """After a choice: the trainer judges each active board's placement; H^ remembers it for credit."""
        now = self.clock
        active = active & self.departure.present(self.played, now)
        events = self.trainer.give(td, action, now, self.played, active)
        self.human.record(td, action, now, active)
        g = self.played.clamp(max=self.games - 1)
        rows = self.rows
        if any(events):
            self.channel.put_events(events)
            count = torch.tensor(
                [[len(e), sum(x.value > 0 for x in e), sum(x.value < 0 for x in e)] for e in events]
            )
            self.given[rows, g] += torch.where(active.unsqueeze(-1), count, 0)
        self.watched[rows, g] += active.to(torch.int64)

    def human_values(self, td: TensorDictBase) -> torch.Tensor:
        """H^ of every placement [L, A]: w . (f(s') - f(s))."""
        return self.human.model(placement_deltas(td))

    def _book(self, nxt: TensorDictBase, active: torch.Tensor) -> bool:
        """Book the games that ended on this step; returns whether any did."""
        done = nxt.get(keys.DONE).view(-1) & active
        if not bool(done.any()):
            return False
        rows = done.nonzero().flatten()
        idx = self.played[rows]
        self.lines[rows, idx] = nxt[keys.LINES].view(-1)[rows]
        self.pieces[rows, idx] = nxt[keys.PIECES_PLACED].view(-1)[rows]
        self.game_ended(done, nxt)
        if self.trainer is not None:
            self.trainer.end_games(done, nxt[keys.LINES].view(-1))
        self.played += done.to(torch.int64)
        return True

    def game_ended(self, done: torch.Tensor, nxt: TensorDictBase) -> None:
        """The games of the boards flagged in ``done`` ended (``nxt``: their last step's output)."""

    def _close_points(self) -> list[Point]:
        points = []
        while self.closed < min(int(self.played.min()), self.games):
            g = self.closed
            s = summarize(self.lines[:, g].double(), floor=0.0)
            record = {
                "game": g + 1,
                "eval/lines_per_game_mean": s["mean"],
                "eval/lines_per_game_median": s["median"],
                "eval/lines_per_game_ci95_low": s["ci95_low"],
                "eval/lines_per_game_ci95_high": s["ci95_high"],
                **self.game_metrics(g),
            }
            points.append(Point(record, g + 1))
            self.closed += 1
        return points

    def feedback_metrics(self, g: int) -> dict[str, float]:
        """Feedback given during game g, over learners."""
        given = self.given.double()
        fb = given[:, g, 0]
        return {
            "feedback/given_mean": float(fb.mean()),
            "feedback/positive_share": float(given[:, g, 1].sum() / fb.sum()) if fb.sum() > 0 else 0.0,
            "feedback/trainer_minutes_mean": float(self.watched[:, g].double().mean())
            * self.seconds_per_placement
            / 60.0,
        }

    def save_due(self) -> bool:
        return self.saves.due(SAVE_EVERY_S)

    # ------------------------------------------------------------ checkpoints

    def checkpoint(self) -> dict[str, Any]:
        state: dict[str, Any] = {
            "env": self.env.state_dict(),
            "lines": self.lines.clone(),
            "pieces": self.pieces.clone(),
            "played": self.played.clone(),
            "given": self.given.clone(),
            "watched": self.watched.clone(),
            "placement": self.placement,
            "closed": self.closed,
            "fusion": self.fusion.state_dict(),
            "learner": self.learner_state(),
        }
        if self.trainer is not None:
            state.update(
                trainer=self.trainer.state_dict(),
                channel=self.channel.state_dict(),
                human=self.human.learner_state(),
                log_seq=self.log.last_seq,  # the last event of each session the learner has been given
            )
        return {"state": state, "policy": self.policy(), "rules": self.rules.as_dict()}

    def widen(self, per_game: torch.Tensor, fill: float = 0) -> torch.Tensor:
        """A saved per-game table [L, G_saved, ...] with room for ``agent.games`` (a longer budget)."""
        missing = self.games - per_game.shape[1]
        if missing <= 0:
            return per_game.clone()
        pad = torch.full((per_game.shape[0], missing, *per_game.shape[2:]), fill, dtype=per_game.dtype)
        return torch.cat((per_game, pad), 1)

    def _load(self, state: dict[str, Any]) -> TensorDictBase:
        td = self.env.load_state_dict(state["env"])
        self.lines, self.pieces = self.widen(state["lines"]), self.widen(state["pieces"])
        self.played, self.given = state["played"].clone(), self.widen(state["given"])
        if "watched" in state:  # checkpoints before trainer.leave_after did not count it
            self.watched = self.widen(state["watched"])
        self.placement, self.closed = int(state["placement"]), int(state["closed"])
        self.fusion.load_state_dict(state["fusion"])
        self.load_learner_state(state["learner"])
        if self.trainer is not None:
            self.trainer.load_state_dict(state["trainer"])
            self.channel.load_state_dict(state["channel"])
            self.human.load_learner_state(state["human"])
            self.log.resume(state["log_seq"], regenerated=True)  # the events after it come again, once
        return td

    def linear_policy(self, features: str, weights: torch.Tensor, note: str) -> dict[str, Any]:
        """A linear afterstate policy over ``features`` (``evaluate.py`` plays it)."""
        return export_policy(
            "linear",
            features=features,
            feature_names=feature_names(feature_id(features), self.rules.width),
            weights=weights.clone(),
            note=note,
        )

    def greedy_evaluation(self, weights: torch.Tensor, features: str, games: int) -> dict[str, float]:
        """Each learner's greedy policy on the same ``games`` fresh games: the mean lines per game of each
        learner, summarised over the learners (the policies without exploration)."""
        gen = component_generator(self.cfg.seed, "eval_games")  # games that training did not play
        seeds = torch.randint(0, 2**62, (games,), generator=gen, dtype=torch.int64)
        rollout = make_rollout(self.cfg, features=features)
        lines, _, _ = rollout(weights.repeat_interleave(games, 0), seeds.repeat(self.learners))
        s = summarize(lines.double().view(self.learners, games).mean(1), floor=0.0)
        return {f"eval/greedy_lines_{k}": s[k] for k in ("mean", "median", "ci95_low", "ci95_high")}

    def final(self) -> dict[str, Any]:
        final = super().final()
        if final and self.trainer is not None:
            final["feedback_events"] = float(self.given[..., 0].sum())
        return final

    def report(self, final: dict[str, Any]) -> list[str]:
        low, high = final["eval/lines_per_game_ci95_low"], final["eval/lines_per_game_ci95_high"]
        lines = [
            f"Done: game {final['game']} of {self.learners} learners: "
            f"{final['eval/lines_per_game_mean']:.1f} "
            f"lines per game (95% CI {low:.1f}..{high:.1f})"
            + (
                f", from {final['feedback_events']:.0f} events of the {self.trainer_label}"
                if self.trainer
                else ""
            )
        ]
        if "eval/greedy_lines_mean" in final:
            g_low, g_high = final["eval/greedy_lines_ci95_low"], final["eval/greedy_lines_ci95_high"]
            lines.append(
                f"Greedy policies:  {final['eval/greedy_lines_mean']:.1f} lines per game over "
                f"{self.cfg.agent.eval_games} fresh games each (95% CI over learners "
                f"{g_low:.1f}..{g_high:.1f})"
            )
        if self.log is not None:
            lines.append(f"Feedback log:     {self.log.path}")
        return lines

    @property
    def trainer_label(self) -> str:
        return TRAINER_LABELS.get(self.cfg.trainer.name, self.cfg.trainer.name)

    def score(self, final: dict[str, Any]) -> float | None:
        return final.get("eval/lines_per_game_mean")

    def hparam_metrics(self, final: dict[str, Any]) -> dict[str, float]:
        return {"hparam/lines_last_game": final["eval/lines_per_game_mean"]}

    def close(self) -> None:
        if self.log is not None:
            self.log.close()


TRAINER_LABELS = {
    "oracle": "simulated oracle trainer",
    "value_proxy": "simulated value-proxy trainer",
    "replay": "replayed feedback log",
    "interactive": "person in the browser",
}
