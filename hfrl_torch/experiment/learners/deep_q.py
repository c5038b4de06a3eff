"""A DQN learner on TorchRL's data path, alone or taught by a trainer: what Tetris and keepaway share.

``train.py agent=dqn [fusion=<scheme>] [human=mlp]``. One learner (one Q network, one H^) plays
``agent.boards`` boards (fields) of a batched env, wrapped as
``TransformedEnv(env, Compose(<domain steps>, <trainer's feedback>, FeedbackFusion(fusion)))``; TorchRL's
``Collector`` steps it with a ``TensorDictSequential`` policy, and ``DQNLoss`` learns from a replay buffer of
its transitions. With a trainer, every step of a collected batch, in time order:

1. H^ remembers the decision of each board (its input, the action, the clock), then learns from the feedback
   the transform delivered in that step's ``next`` (credit over the recent decisions);
2. the policy chose it through the one fusion component: Q (``keys.ENV_VALUES``) and H^
   (``keys.HUMAN_VALUES``) into ``FusionModule`` (greedy on the fused values), then TorchRL's
   ``EGreedyModule`` explores (not for ``human_only``: TAMER acts greedily on H^), and H^ of the action taken
   goes to ``FeedbackFusion`` for reward-level rules (``reward_shaping``: the DQN learns from r + w H^);
3. each game (episode) that ended ends the learner's fusion episode: ``Fusion.end_episode`` with its lines
   (hold seconds): eq. 4.4 for the trust factor, the bandit's score for ``fusion.weight=adaptive``.

The DQN always learns from the reward ``FeedbackFusion`` hands it (the environment's own for decision-level
rules), and learns during ``human_only`` runs too, where it never acts (Deep TAMER alone). The curve has one
point every ``agent.eval_every`` frames: the greedy policy (no exploration; the fusion in evaluation mode)
on the same fresh episodes each time, plus what training saw. Checkpoints hold both networks, Adam's
moments, H^ (with Deep TAMER's feedback buffer), the fusion, the transforms' state (trainer, channel,
episode counts) and the random state; the DQN's own replay buffer is not saved (tens of megabytes), so a
resumed run refills it for ``agent.learn_after`` frames, and the games in progress restart.
"""

from __future__ import annotations

import math
from abc import abstractmethod
from pathlib import Path
from typing import Any, ClassVar

import torch
from omegaconf import DictConfig
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.collectors import Collector
from torchrl.envs import Compose, EnvBase, TransformedEnv
from torchrl.envs.transforms import Transform
from torchrl.modules import EGreedyModule

from hfrl_torch import keys
from hfrl_torch.agents.dqn import ChosenEstimate, DeepQ, HumanValues, HumanValuesModule
from hfrl_torch.common.logger import Logger
from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.stats import summarize
from hfrl_torch.experiment.factories import FeedbackWiring, make_feedback_wiring, make_fusion
from hfrl_torch.experiment.learners.tetris_games import TRAINER_LABELS
from hfrl_torch.experiment.run import FramesLearner, Point, WallClockSaves
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.transform import FeedbackFusion, FusionModule
from hfrl_torch.interactive.live import LiveTeaching, taught_by_person
from hfrl_torch.trainers.departure import Departure

SAVE_EVERY_S = 10.0  # wall seconds between checkpoints


class CollectorLearner(FramesLearner):
    """What the learners whose policy TorchRL's ``Collector`` runs on B boards, alone or taught, share
    (:class:`DeepQLearner`, ``gym_ppo.GymPPO``): the budget in frames, a taught point's feedback fields,
    the checkpoint's common state, the fusion's payload and the report. Their ``__init__`` sets the counts
    (``frames``, ``points``, ``episodes``, ``events``, ``positive``, ``trainer_seconds``,
    ``weights_played``), ``taught``, ``fusion``, ``reward_fusion``, ``saves`` and, taught, ``human``,
    ``feedback_transform``, ``log`` and, when a person teaches from the browser, ``teaching``."""

    score_key: ClassVar[str] = ""  # the greedy evaluation's main metric
    score_unit: ClassVar[str] = ""
    episode_word: ClassVar[str] = "episode"

    @property
    def eval_episodes(self) -> int:
        return int(self.cfg.agent.eval_episodes)

    # ------------------------------------------------------------ a person's page

    @property
    def who(self) -> str:
        """Who gives the feedback, for the run's TensorBoard text."""
        if self.teaching is not None:
            return taught_by_person("board 0")
        label = TRAINER_LABELS.get(self.cfg.trainer.name, self.cfg.trainer.name)
        leaves = self.feedback_transform.departure.describe() if self.feedback_transform is not None else ""
        return f"{label} (a simulated or replayed trainer, not a person), one per board; {leaves}"

    def save_due(self) -> bool:
        return self.saves.due(SAVE_EVERY_S)

    @abstractmethod
    def greedy_evaluation(self) -> dict[str, float]:
        """The greedy policy on the evaluation episodes (the same ones at every point)."""

    @abstractmethod
    def agent_record(self) -> dict[str, float]:
        """A point's fields of the agent's own learning since the last point (its losses, its updates)."""

    def _point(self) -> Point:
        """The curve's next point: the greedy evaluation, the training episodes and the agent's learning since
        the last point and, taught, the feedback; the tallies since the last point start again."""
        evaluation = self.greedy_evaluation()
        done = summarize(torch.tensor(self.finished, dtype=torch.float64), floor=0.0) if self.finished else {}
        record: dict[str, Any] = {
            "frames": self.frames,
            **evaluation,
            f"train/{self.episode_word}s": self.episodes,
            f"train/{self.score_key.split('/')[-1].replace('greedy_', '')}": done.get("mean", math.nan),
            **self.agent_record(),
        }
        if self.taught:
            record.update(self.feedback_record())
        self.finished, self.losses, self.weights_played = [], [], []
        self.points += 1
        return Point(record, self.frames)

    def feedback_record(self) -> dict[str, float]:
        """A taught point's feedback fields: the events, the trainer's minutes and the weight on H^ (now, and
        the mean the episodes ended since the last point played at)."""
        weight, played = float(self.fusion.weight()[0]), self.weights_played
        return {
            "feedback_events": float(self.events),
            "trainer_minutes": self.trainer_seconds / 60.0,
            "weight": weight,
            "feedback/positive_share": self.positive / self.events if self.events else 0.0,
            "fusion/weight_mean": weight,
            "fusion/played_weight_mean": sum(played) / len(played) if played else math.nan,
            "trainer/present": float(self.feedback_transform.present),
        }

    def common_state(self) -> dict[str, Any]:
        """The checkpoint's state besides the agent's own: the counts, the fusion, the reward fusion, the
        random state and, taught, H^, the feedback transform and the log's last event."""
        state: dict[str, Any] = {
            "frames": self.frames,
            "points": self.points,
            "episodes": self.episodes,
            "events": [self.events, self.positive],
            "trainer_seconds": self.trainer_seconds,
            "fusion": self.fusion.state_dict(),
            "reward_fusion": self.reward_fusion.get_extra_state(),
            "rng": torch.get_rng_state(),
        }
        if self.taught:
            state.update(
                human=self.human.state_dict(),
                feedback=self.feedback_transform.get_extra_state(),
                log_seq=self.log.last_seq,
            )
        return state

    def load_common_state(self, state: dict[str, Any]) -> None:
        """Resume what :meth:`common_state` saved: a simulated trainer's or a replay's events after it come
        again and are logged once; a person's presses logged after it go to the channel, to be learned once
        (they watch board 0)."""
        self.frames, self.points, self.episodes = (int(state[k]) for k in ("frames", "points", "episodes"))
        self.events, self.positive = (int(v) for v in state["events"])
        self.trainer_seconds = float(state["trainer_seconds"])
        self.fusion.load_state_dict(state["fusion"])
        self.reward_fusion.set_extra_state(state["reward_fusion"])
        torch.set_rng_state(state["rng"])
        if self.taught:
            self.human.load_state_dict(state["human"])
            self.feedback_transform.set_extra_state(state["feedback"])
            # a person's presses logged after the checkpoint (or recovered from the journal): learned now
            unseen = self.log.resume(state["log_seq"], regenerated=self.teaching is None)
            self.feedback_transform.put_board(0, unseen, self.boards)

    def fusion_payload(self) -> dict[str, Any] | None:
        """How ``evaluate.py`` fuses the saved H^ with the agent's values (Q, or the policy's logits; None:
        the agent alone)."""
        if not self.taught:
            return None
        return {
            "scheme": self.fusion.decision,
            "scaling": self.fusion.scaling,
            "weight": float(self.fusion.weight()[0]),
            "q_spread": float(self.fusion.q_spread[0]),
            "human": str(self.cfg.human.name),
        }

    def report(self, final: dict[str, Any]) -> list[str]:
        low, high = final.get(f"{self.score_key}_ci95_low"), final.get(f"{self.score_key}_ci95_high")
        lines = [
            f"Done: {final['frames']} frames; greedy policy {final[f'{self.score_key}_mean']:.2f} "
            f"{self.score_unit} (95% CI {low:.2f}..{high:.2f} over {self.eval_episodes} fresh "
            f"{self.episode_word}s)"
        ]
        curve = [r for r in self.history if self.x_key in r]
        if len(curve) > 1:
            shown = ", ".join(f"{r[f'{self.score_key}_mean']:.1f}" for r in curve)
            lines.append(f"Curve (greedy {self.score_unit} every {self.eval_every} frames): {shown}")
        if self.taught:
            lines.append(
                f"Feedback:         {self.events} events of the "
                f"{TRAINER_LABELS.get(self.cfg.trainer.name, self.cfg.trainer.name)} "
                f"(fusion={self.cfg.fusion.name}, human={self.cfg.human.name}, "
                f"weight on H^ now {float(self.fusion.weight()[0]):.2f})"
            )
            lines.append(f"Feedback log:     {self.log.path}")
        return lines

    def score(self, final: dict[str, Any]) -> float | None:
        return final.get(f"{self.score_key}_mean")

    def hparam_metrics(self, final: dict[str, Any]) -> dict[str, float]:
        return {f"hparam/{self.score_key.split('/')[-1]}": final[f"{self.score_key}_mean"]}


class DeepQLearner(CollectorLearner):
    """The collector loop of one DQN learner on B boards (see the module docstring)."""

    agent = "dqn"

    def __init__(self, cfg: DictConfig, run_dir: Path, checkpoint: dict[str, Any] | None = None) -> None:
        super().__init__(cfg, run_dir, checkpoint)
        a = cfg.agent
        self.seed = int(cfg.seed)
        torch.manual_seed(component_seed(self.seed, "agent"))  # network initialisation, TorchRL's exploration
        self.boards, self.steps_per_batch = int(a.boards), int(a.steps_per_batch)
        self.frames_total, self.eval_every = int(a.frames), int(a.eval_every)
        self.taught = cfg.trainer.name != "none"
        self.log: FeedbackLog | None = None
        self.fusion: Fusion = make_fusion(cfg, type(self), 1)
        self.dqn = self.make_dqn()
        self.human: HumanValues | None = self.make_human() if self.taught else None
        self.feedback_transform = None
        self.teaching: LiveTeaching | None = None
        if self.taught:  # the trainer's transform keeps its own channel: its boards are the env's
            wiring = self.make_wiring(run_dir)
            self.log, self.teaching = wiring.log, wiring.teaching
            self.feedback_transform = self.make_feedback(wiring.trainer, wiring.departure)
        self.reward_fusion = FeedbackFusion(self.fusion, estimate_key=keys.HUMAN_REWARD_ESTIMATE)
        parts = [*self.domain_transforms(), *filter(None, [self.feedback_transform]), self.reward_fusion]
        self.env = TransformedEnv(
            self.make_env(self.boards, component_seed(self.seed, "env")), Compose(*parts), auto_unwrap=True
        )
        self.explore = None
        if self.fusion.explores:
            self.explore = EGreedyModule(
                self.env.action_spec.clone(),
                eps_init=float(a.epsilon_start),
                eps_end=float(a.epsilon_end),
                annealing_num_steps=max(1, int(float(a.epsilon_frames) / self.frames_per_batch)),
                action_mask_key=self.mask_key if self.masked else None,
            )
        self.greedy_policy = self.make_policy(explore=False)
        self.policy = self.make_policy(explore=True)
        self.frames = 0
        self.points = 0
        self.updates_per_batch = max(1, round(self.frames_per_batch / float(a.frames_per_update)))
        self.losses: list[float] = []
        self.finished: list[float] = []  # performance of the training episodes ended since the last point
        self.episodes = 0
        self.events = 0
        self.positive = 0
        self.weights_played: list[float] = []
        self.trainer_seconds = 0.0
        if checkpoint is not None:
            self._load(checkpoint["state"])
        self.collector = Collector(
            self.env,
            self.policy,
            frames_per_batch=self.frames_per_batch,
            total_frames=-1,
            auto_register_policy_transforms=False,
        )
        self.batches = iter(self.collector)
        self.saves = WallClockSaves()
        self.logger: Logger | None = None

    # ------------------------------------------------------------------ domain

    masked: ClassVar[bool] = False  # the actions' mask matters (Tetris placements)
    mask_key: ClassVar[Any] = keys.ACTION_MASK
    human_in_keys: ClassVar[list[Any]] = []

    @abstractmethod
    def make_env(self, boards: int, seed: int) -> EnvBase:
        """The batched env (``boards`` boards, seeded)."""

    def domain_transforms(self) -> list[Transform]:
        """Transforms before the trainer's (keepaway: the team's SMDP reward)."""
        return []

    @abstractmethod
    def make_dqn(self) -> DeepQ:
        """The DQN learner of ``agent``."""

    @abstractmethod
    def make_human(self) -> HumanValues:
        """H^ of ``human``, shared by the boards."""

    @abstractmethod
    def make_trainer(self, log: FeedbackLog) -> Any:
        """The simulated (or replayed) trainer of ``trainer``, logging to ``log``."""

    def make_wiring(self, run_dir: Path) -> FeedbackWiring:
        """The run's feedback wiring (``make_feedback_wiring``): the log and :meth:`make_trainer`'s trainer. A
        domain whose page a person teaches on (``trainer=interactive``) passes its page's trainer too."""
        return make_feedback_wiring(self.cfg, run_dir, self.fusion, self.make_trainer, fsync_simulated=False)

    @abstractmethod
    def make_feedback(self, trainer: Any, departure: Departure) -> Transform:
        """``trainer`` as a transform (writes ``keys.FEEDBACK*`` and ``keys.CLOCK`` into ``next``) that stops
        judging at ``departure`` (``trainer.leave_after``)."""

    @abstractmethod
    def episode_performance(self, nxt: TensorDictBase) -> torch.Tensor:
        """Each board's performance ``[B]`` for the episode that ended at this step (lines, hold seconds)."""

    def fusion_performance(self, performance: float) -> float:
        """What an ended episode's performance counts for in the fusion's weight (eq. 4.4, the bandit), which
        needs it >= 0: the performance itself here (lines, hold seconds)."""
        return performance

    @abstractmethod
    def policy_payload(self) -> dict[str, Any]:
        """What ``evaluate.py`` plays: the checkpoint's ``"policy"``, written with
        :func:`~hfrl_torch.agents.policies.export_policy`."""

    @abstractmethod
    def watched_seconds(self, nxt: TensorDictBase) -> float:
        """Seconds of play the trainers watched in one step of every board (the human effort)."""

    # ------------------------------------------------------------------ policy

    @property
    def frames_per_batch(self) -> int:
        return self.boards * self.steps_per_batch

    def make_policy(self, explore: bool) -> TensorDictSequential:
        """Q (and, with a trainer, H^ and the fusion component) to an action; exploration on top."""
        modules: list[TensorDictModuleBase] = [*self.dqn.pre, self.dqn.q]
        if self.taught:
            modules += [
                HumanValuesModule(self.human, self.human_in_keys),
                FusionModule(self.fusion, "greedy"),
            ]
        else:
            modules.append(self.dqn.greedy)
        if explore and self.explore is not None:
            modules.append(self.explore)
        if self.taught:
            modules.append(ChosenEstimate())
        return TensorDictSequential(*modules)

    # ---------------------------------------------------------------- the loop

    @property
    def description(self) -> str:
        return f"DQN {self.domain}" + (f" + {self.cfg.fusion.name}" if self.taught else "")

    def start(self, logger: Logger) -> None:
        self.logger = logger
        if self.taught and not self.resumed:
            logger.text("trainer", f"{self.who}; fusion={self.cfg.fusion.name}, human={self.cfg.human.name}")

    def advance(self) -> list[Point]:
        if self.points == 0 and not self.resumed and self.frames == 0:
            return [self._point()]  # the untrained policy: where every curve starts
        goal = min(self.frames_total, (self.points) * self.eval_every)
        while self.frames < goal and not self.ending:
            self._learn_batch(next(self.batches))
        if self.frames < goal:  # ended early: the checkpoint keeps the frames; resumed, the chunk goes on
            return []
        return [self._point()]

    def _learn_batch(self, batch: TensorDictBase) -> None:
        """One collected batch [B, T]: H^ and the fusion's episodes in time order, then DQN updates."""
        a = self.cfg.agent
        for t in range(batch.shape[1]):
            step = batch[:, t]
            nxt = step["next"]
            if self.taught:
                self.human.record(step, step[keys.ACTION], step[keys.CLOCK])
                count = self.human.learn(nxt)
                self.events += int(count.sum())
                given = nxt[keys.FEEDBACK_MASK]
                self.positive += int((given & (nxt[keys.FEEDBACK] > 0)).sum())
                if self.feedback_transform.present_at(self.episodes, step[keys.CLOCK]):
                    self.trainer_seconds += self.watched_seconds(nxt)
            done = nxt[keys.DONE].reshape(-1)
            if bool(done.any()):
                perf = self.episode_performance(nxt)[done]
                for p in perf.tolist():
                    if self.taught:
                        self.weights_played.append(float(self.fusion.weight()[0]))
                        self.fusion.end_episode(torch.ones(1, dtype=torch.bool), self.fusion_performance(p))
                    self.finished.append(float(p))
                self.episodes += int(done.sum())
        self.dqn.extend(batch)
        self.frames += batch.numel()
        if self.explore is not None:
            self.explore.step()
        if len(self.dqn.buffer) >= max(int(a.learn_after), 1):  # after a resume, the buffer refills first
            for _ in range(self.updates_per_batch):
                self.losses.append(self.dqn.update())

    def agent_record(self) -> dict[str, float]:
        return {
            "train/loss": sum(self.losses) / len(self.losses) if self.losses else math.nan,
            "train/epsilon": float(self.explore.eps) if self.explore is not None else 0.0,
            "train/updates": self.dqn.updates,
        }

    # ------------------------------------------------------------- checkpoints

    def checkpoint(self) -> dict[str, Any]:
        state = self.common_state()
        state.update(
            dqn=self.dqn.state_dict(), explore=None if self.explore is None else self.explore.state_dict()
        )
        return {"state": state, "policy": self.policy_payload()}

    def _load(self, state: dict[str, Any]) -> None:
        self.dqn.load_state_dict(state["dqn"])
        if self.explore is not None:
            self.explore.load_state_dict(state["explore"])
        self.load_common_state(state)

    # ------------------------------------------------------------------ results

    def close(self) -> None:
        self.collector.shutdown()
        self.end_teaching("agent.frames", 2 * self.frames_total)
        if self.log is not None:
            self.log.close()
