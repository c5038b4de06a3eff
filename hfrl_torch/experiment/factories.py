"""``make_*`` factories: the objects of a run, built from its config (checked beforehand by ``config.py``)."""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numba
import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDict, TensorDictBase
from tensordict.nn import TensorDictModule

from hfrl_torch import keys
from hfrl_torch.agents.cem import CEMConfig
from hfrl_torch.agents.cem.cem import Rollout
from hfrl_torch.agents.dqn import DeepQ, SharedTileTamer
from hfrl_torch.agents.policies import load_policy
from hfrl_torch.agents.sarsa import SarsaLambda, sarsa_keepers
from hfrl_torch.agents.sarsa.policy import load_keeper_policy
from hfrl_torch.agents.tamer import TamerAgent
from hfrl_torch.agents.tamer.deep_tamer import DeepTamer
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.imports import load_callable
from hfrl_torch.common.seeding import component_generator, component_seed
from hfrl_torch.common.threads import available_threads
from hfrl_torch.envs.gym_task import GymTask
from hfrl_torch.envs.keepaway import KeepawayConfig, saved_config
from hfrl_torch.envs.tetris import engine_torch
from hfrl_torch.envs.tetris.engine_numba import play as numba_play
from hfrl_torch.envs.tetris.env import TetrisEnv
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.experiment.run import Learner
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.feedback.credit import CreditModel, GammaDelay, PreviousStep, UniformDelay
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight
from hfrl_torch.fusion.weights import make_weight
from hfrl_torch.interactive.explain import WEIGHT_NAME, weight_sentence
from hfrl_torch.interactive.gym_live import BrowserGymTrainer
from hfrl_torch.interactive.journal import JOURNAL_NAME, PressJournal
from hfrl_torch.interactive.keepaway_live import BrowserKeeperTrainer
from hfrl_torch.interactive.live import DEFAULT_SPEED, KEY_NAMES, LiveTeaching
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import TeachingSession
from hfrl_torch.interactive.tetris_live import BrowserTetrisTrainer
from hfrl_torch.interactive.timeline import REACTION_S
from hfrl_torch.models.tile_coding import TileCoding, keepaway_tile_widths
from hfrl_torch.trainers import HumanLikeTiming, OracleTrainer, ReplayTrainer, Trainer, ValueProxyTrainer
from hfrl_torch.trainers.departure import Departure
from hfrl_torch.trainers.keepaway_oracle import KeepawayOracle
from hfrl_torch.trainers.keepaway_replay import KeepawayReplay
from hfrl_torch.trainers.reference_oracle import Reference, ReferenceOracle
from hfrl_torch.trainers.reference_value_proxy import ReferenceValueProxy

# ------------------------------------------------------------------------------- run


def make_device(cfg: DictConfig) -> torch.device:
    """The torch device named by ``device``."""
    return torch.device(cfg.device)


def set_threads(cfg: DictConfig) -> int:
    """Apply ``threads`` (a count, or ``auto``: every core this process may use) to the compiled kernels
    (games, boards and fields run in parallel over threads); torch keeps one intra-op thread: its ops here
    are small, and a second thread's spin-waits took the other core from the kernels (CE at ``threads=2``:
    33.1 s against 27.5 s with torch at one)."""
    n = available_threads() if cfg.threads == "auto" else int(cfg.threads)
    n = min(n, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(n)
    torch.set_num_threads(1)  # last: numba's OpenMP layer can reset torch's thread count
    return n


# ---------------------------------------------------------------------------- tetris


def make_rules(cfg: DictConfig) -> TetrisRules:
    """Tetris rules from ``domain``."""
    d = cfg.domain
    return TetrisRules(
        width=d.width, height=d.height, bag=d.bag, spawn_topout=d.spawn_topout, preview=d.preview
    )


def make_env(
    cfg: DictConfig, batch: int, features: str | None = None, max_pieces: int | None = None
) -> TetrisEnv:
    """A batched ``TetrisEnv`` from ``domain`` and ``device``."""
    return TetrisEnv(
        batch=batch,
        rules=make_rules(cfg),
        features=features or cfg.domain.features,
        engine=cfg.domain.engine,
        max_pieces=cfg.domain.max_pieces if max_pieces is None else max_pieces,
        device=make_device(cfg),
        seed=component_seed(cfg.seed, "env"),
    )


def make_rollout(cfg: DictConfig, features: str | None = None, random_policy: bool = False) -> Rollout:
    """Whole-game rollouts of linear policies (or uniformly random placements) on the configured engine."""
    rules = make_rules(cfg)
    fid = feature_id(features or cfg.domain.features)
    device = make_device(cfg)
    engine = cfg.domain.engine
    if engine == "auto":
        engine = "numba" if device.type == "cpu" else "torch"
    max_pieces = cfg.domain.max_pieces

    def play(*args: object, **kwargs: object) -> tuple[torch.Tensor, ...]:
        if engine == "numba":
            return numba_play(*args, **kwargs)
        return engine_torch.play(*args, device=device, **kwargs)

    def rollout(
        weights: torch.Tensor, seeds: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        lines, pieces, capped = play(
            rules, fid, weights, seeds, max_pieces=max_pieces, random_policy=random_policy
        )
        return lines.cpu(), pieces.cpu(), capped.cpu()

    return rollout


def warm_up(cfg: DictConfig, features: str | None = None) -> None:
    """Load (or compile) the engine's kernels with a one-piece game, so that timings measure play."""
    name = features or cfg.domain.features
    n = feature_size(feature_id(name), cfg.domain.width)
    one_piece = make_rollout(OmegaConf.merge(cfg, {"domain": {"max_pieces": 1}}), features=name)
    one_piece(torch.zeros(1, n, dtype=torch.float64), torch.zeros(1, dtype=torch.int64))


def make_cem_config(cfg: DictConfig) -> CEMConfig:
    """CE settings from ``agent``."""
    a = cfg.agent
    names = [f.name for f in dataclasses.fields(CEMConfig)]
    return CEMConfig(**{k: a[k] for k in names})


# ---------------------------------------------------------------------- feedback, H^


def make_credit(cfg: DictConfig) -> CreditModel:
    """H^'s credit assignment from ``human.credit``."""
    h = cfg.human
    if h.credit == "previous_step":
        return PreviousStep()
    if h.credit == "gamma":
        return GammaDelay(h.gamma_shape, h.gamma_scale)
    return UniformDelay(h.uniform_low, h.uniform_high)


def make_tamer(cfg: DictConfig, learners: int, num_features: int) -> TamerAgent:
    """H^ over Tetris features (TAMER), one learner per board."""
    h = cfg.human
    return TamerAgent(num_features, learners, h.alpha, make_credit(cfg), h.window, h.renormalise)


def keeper_tamer_on(cfg: DictConfig, model: TileCoding, fields: int, kernels: str = "torch") -> KeeperTamer:
    """Keepaway TAMER over ``model`` for ``fields`` fields, with ``human``'s step size, credit and window
    (``kernels``: torch, or numba for H^'s sums and adds compiled)."""
    h = cfg.human
    return KeeperTamer(
        model,
        fields,
        alpha=h.alpha,
        credit=make_credit(cfg),
        window=h.window,
        history=h.history,
        renormalise=h.renormalise,
        kernels=kernels,
    )


def make_keeper_tamer(
    cfg: DictConfig, agent: SarsaLambda, fields: int, keepers: int
) -> tuple[KeeperTamer, torch.Tensor]:
    """H^ on the Sarsa keepers' own tile coding (and their kernels), and the H^ model of each agent row
    (team or keeper)."""
    per_keeper = cfg.human.model == "keeper"
    coder = agent.coder
    model = TileCoding(
        coder.widths.tolist(),
        num_actions=coder.num_actions,
        learners=fields * keepers if per_keeper else fields,
        tilings=coder.tilings,
        size=coder.size,
        device=coder.weight.device,
    )
    tamer = keeper_tamer_on(cfg, model, fields, agent.kernels)
    rows = torch.arange(fields * keepers)
    owners = rows if per_keeper else torch.div(rows, keepers, rounding_mode="floor")
    return tamer, owners


def make_trainer(cfg: DictConfig, log: FeedbackLog | None) -> Trainer | None:
    """The simulated Tetris trainer (or replay) of ``trainer``, logging every event it gives to ``log``."""
    t = cfg.trainer
    if t.name == "none":
        return None
    if t.name == "replay":
        return make_replay(cfg, log)
    if t.name == "oracle":
        base: Trainer = OracleTrainer(
            frequency=t.frequency,
            consistency=t.consistency,
            seed=component_seed(cfg.seed, "trainer"),
            reaction=t.reaction,
        )
    else:
        base = ValueProxyTrainer(mode=t.mode, scale=t.scale, reaction=t.reaction)
    return with_timing(cfg, base, log)


def make_replay(cfg: DictConfig, log: FeedbackLog | None) -> Trainer:
    """``trainer=replay`` wherever events are matched by (board, episode, step): Tetris's placements and any
    Gymnasium task's ``StepCounter`` steps, each event of ``trainer.log`` given again at the same step."""
    return with_timing(cfg, ReplayTrainer.from_log(cfg.trainer.log, reaction=cfg.trainer.reaction), log)


def with_timing(cfg: DictConfig, base: Trainer, log: FeedbackLog | None) -> Trainer:
    """``base`` with ``trainer.timing``'s human-like delays, fatigue, bias and absences when enabled (the
    log goes to the outer trainer)."""
    timing = cfg.trainer.timing
    if not timing.enabled:
        base.log = log
        return base
    return HumanLikeTiming(
        base,
        delay=GammaDelay(timing.delay_shape, timing.delay_scale),
        fatigue_tau=timing.fatigue_tau,
        positive_bias=timing.positive_bias,
        absence=timing.absence,
        tail_lines=timing.tail_lines,
        seed=component_seed(cfg.seed, "timing"),
        log=log,
    )


def make_departure(cfg: DictConfig) -> Departure:
    """When the simulated trainer leaves (``trainer.leave_after``, ``trainer.leave_unit``); a person leaves
    the page whenever they like, so ``trainer=interactive`` never leaves by config."""
    t = cfg.trainer
    after = OmegaConf.select(cfg, "trainer.leave_after")
    if t.name in ("none", "interactive") or after is None:
        return Departure()
    return Departure(float(after), str(t.get("leave_unit", "episodes")))


def make_reference_keepers(
    cfg: DictConfig, config: KeepawayConfig
) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None:
    """The keepaway oracle's reference: None (the hand-coded keepers) or a learned checkpoint's greedy keepers
    as ``(obs, keeper) -> actions`` (field f is judged against the checkpoint's team f % its teams)."""
    reference = OmegaConf.select(cfg, "trainer.reference")
    if reference in (None, "hand"):
        return None
    choose, _ = load_keeper_policy(
        load_checkpoint(str(reference), domain="keepaway"),
        "cpu",
        component_generator(cfg.seed, "reference"),
    )

    def reference_actions(obs: torch.Tensor, keeper: torch.Tensor) -> torch.Tensor:
        return choose(obs, torch.ones(obs.shape[0], config.num_actions, dtype=torch.bool), keeper)

    return reference_actions


def make_keeper_trainer(
    cfg: DictConfig, config: KeepawayConfig, fields: int, log: FeedbackLog | None
) -> KeepawayOracle | KeepawayReplay:
    """Who judges the keepers: the simulated oracle or a replayed log (a person: ``make_live_teaching``)."""
    t = cfg.trainer
    if t.name == "interactive":
        raise ValueError("trainer=interactive: the person's trainer comes with the page (make_live_teaching)")
    if t.name == "replay":
        return KeepawayReplay.from_log(str(t.log), fields, log)
    timing = t.timing
    on = bool(timing.enabled)
    return KeepawayOracle(
        config.keepers,
        config.takers,
        frequency=t.frequency,
        consistency=t.consistency,
        delay=GammaDelay(timing.delay_shape, timing.delay_scale) if on else float(t.reaction),
        seed=component_seed(cfg.seed, "trainer"),
        log=log,
        fatigue_tau=timing.fatigue_tau if on else None,
        positive_bias=float(timing.positive_bias) if on else 0.0,
        absence=float(timing.absence) if on else 0.0,
        reference=make_reference_keepers(cfg, config),
    )


LiveTrainer = BrowserTetrisTrainer | BrowserKeeperTrainer | BrowserGymTrainer


def make_live_teaching(
    cfg: DictConfig,
    view: str,
    fusion: Fusion,
    drain: Callable[[TeachingSession], LiveTrainer],
    speed: float | None = None,
    info: Mapping[str, Any] | None = None,
) -> LiveTeaching:
    """The browser trainer's page server for ``view`` (tetris, keepaway or gym), started, with ``drain``'s
    trainer taking the presses off the session and logging them; with a log, each press is journaled on disk
    before the page is told it was taken, and a killed run's presses the log lacks are logged now
    (``journal.py``). The page says what sets ``fusion``'s weight in its own words, unless ``trainer.blind``
    (a study's participant): then no message names the fusion or carries its weight. ``speed``: the
    starting speed when ``trainer.actions_per_s`` is null (None: the view's ``DEFAULT_SPEED``); ``info``:
    what else the page is told once (e.g. the words of its curve's axes)."""
    t = cfg.trainer
    default = DEFAULT_SPEED[view] if speed is None else speed
    speed = default if t.actions_per_s is None else float(t.actions_per_s)
    reaction = OmegaConf.select(t, "reaction_s", default=None)  # runs saved before it existed: REACTION_S
    blind = bool(OmegaConf.select(t, "blind", default=False))  # runs saved before it existed: not blind
    session = TeachingSession(
        actions_per_s=speed,
        reconnect_s=float(t.reconnect_wait_s),
        reaction_s=REACTION_S if reaction is None else float(reaction),
        blind=blind,
    )
    session.set_live(False)  # nothing to judge until the learner shows its game (start-up takes seconds)
    session.info = dict(info or {})
    if not blind:  # TAMER alone (fusion=none) acts on H^ alone, as fusion=human_only does
        scheme = "human_only" if fusion.decision == "human_only" else str(cfg.fusion.name)
        session.info |= {
            "weight_name": WEIGHT_NAME,
            "weight_sentence": weight_sentence(scheme, fusion.describe_weight, view),
        }
    server = TeachingServer(
        session,
        host=t.host,
        port=int(t.port),
        token=t.token,
        keys={k: str(t["keys"][k]) for k in KEY_NAMES},
        view=view,
        max_message_bytes=int(t.max_message_bytes),
        max_messages_per_s=float(t.max_messages_per_s),
        max_teachers=int(t.max_teachers),
        max_connections=int(t.max_connections),
    )
    trainer = drain(session)
    if trainer.log is not None:
        path = trainer.log.path.with_name(JOURNAL_NAME)
        session.journal = PressJournal(path, trainer.log, session.reaction_s, trainer.discrete)
    return LiveTeaching.start(server, session, trainer)


@dataclass
class FeedbackWiring:
    """What carries one run's feedback to its learner: the log every event is written to, the trainer (a
    simulated one, a replayed log, or a person's presses drained from the page), the channel its events wait
    in on each board's clock, when a simulated trainer leaves, and the page server when a person teaches."""

    log: FeedbackLog
    trainer: Any
    channel: FeedbackChannel | None
    departure: Departure
    teaching: LiveTeaching | None = None


def make_feedback_wiring(
    cfg: DictConfig,
    run_dir: Path,
    fusion: Fusion,
    simulated: Callable[[FeedbackLog], Any],
    live: Callable[[TeachingSession, FeedbackLog], LiveTrainer] | None = None,
    view: str = "tetris",
    boards: int | None = None,
    fsync_simulated: bool = True,
    speed: float | None = None,
    info: Mapping[str, Any] | None = None,
) -> FeedbackWiring:
    """The feedback wiring of every learner with a trainer, built in one place: the run's
    ``feedback.jsonl`` (a person's presses are fsync'd one by one, as they cannot be regenerated; simulated
    events where ``fsync_simulated``), the trainer (``live``'s drain of the page for ``trainer=interactive``,
    with the page's ``view``, starting ``speed`` and ``info``: :func:`make_live_teaching`; else
    ``simulated``'s), a channel of ``boards`` boards (None: the learner's transform keeps its own) and the
    trainer's departure."""
    person = cfg.trainer.name == "interactive"
    log = FeedbackLog(run_dir / "feedback.jsonl", session=run_dir.name, fsync=person or fsync_simulated)
    teaching = None
    if person:
        if live is None:
            raise ValueError(f"trainer=interactive has no page for view {view!r}")
        teaching = make_live_teaching(cfg, view, fusion, lambda session: live(session, log), speed, info)
        trainer = teaching.trainer
    else:
        trainer = simulated(log)
    channel = None if boards is None else FeedbackChannel(boards)
    return FeedbackWiring(log, trainer, channel, make_departure(cfg), teaching)


# ------------------------------------------------------------------------------ fusion


def fusion_scaling(cfg: DictConfig, default: str = "decision") -> str:
    """How R and H^ are put on one scale (``fusion.normalise``): true rescales both per decision, false fuses
    the raw values, spread scales H^ by Q's running spread; null is the learner's own way (``default``,
    ``Learner.default_scaling``: Tetris CE per decision, keepaway H^ times Q's spread, PG raw)."""
    value = OmegaConf.select(cfg, "fusion.normalise") if "normalise" in cfg.fusion else False
    if value is True:
        return "decision"
    if value is False:
        return "none"
    return default if value is None else str(value)


def make_fusion(
    cfg: DictConfig,
    learner: type[Learner],
    learners: int = 1,
    option: str | None = None,
) -> Fusion:
    """The one fusion component of a run of ``learner``: ``fusion``'s rules, the weight for what the learner
    gives it (``Learner.weight_evidence``) and the scale (``Learner.default_scaling`` unless
    ``fusion.normalise`` says), for ``learners`` learners (``option``: a learner's own rule instead, e.g.
    TAMER's ``human_only``); its draws are the run's ``fusion`` stream. With ``agent.greedy_with_bandit``
    (the Sarsa keepers) a learner whose weight a bandit chooses acts greedily on the fused values."""
    seed = component_seed(cfg.seed, "fusion")
    if option is not None and option != cfg.fusion.name:
        return Fusion.from_option(option, ConstantWeight([0.0] * learners), seed=seed)
    schedule = make_weight(cfg, learners, learner.weight_evidence)
    scaling = fusion_scaling(cfg, learner.default_scaling)
    explore = schedule.kind != "bandit" or not cfg.agent.get("greedy_with_bandit", False)
    return Fusion.from_option(cfg.fusion.name, schedule, scaling=scaling, seed=seed, explore=explore)


# ---------------------------------------------------------------------------- keepaway


def make_keepaway_config(cfg: DictConfig) -> KeepawayConfig:
    """The simulator's ``KeepawayConfig`` from ``domain`` (every field it has that ``domain`` sets; a saved
    run's ``domain`` that predates the perception options plays the exact task it was trained on)."""
    names = {f.name for f in dataclasses.fields(KeepawayConfig)}
    values = {k: v for k, v in OmegaConf.to_container(cfg.domain, resolve=True).items() if k in names}
    values["preset"] = str(values["preset"])
    return saved_config(values)


def make_keepers(cfg: DictConfig, config: KeepawayConfig, device: torch.device) -> SarsaLambda:
    """The Sarsa keepers of ``agent`` for ``agent.learners`` teams of ``agent.fields_per_learner`` fields."""
    a = cfg.agent
    return sarsa_keepers(
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
        seed=component_seed(cfg.seed, "agent"),
        device=device,
        kernels=str(a.get("kernels", "auto")),
    )


# -------------------------------------------------------------------------- deep learners


def make_dqn(
    cfg: DictConfig,
    model: torch.nn.Module,
    in_key: str,
    mask_key: str | None,
    pre: tuple[TensorDictModule, ...] = (),
) -> DeepQ:
    """The DQN of ``agent`` (TorchRL's loss, target and replay buffer) around the Q network ``model``."""
    a = cfg.agent
    return DeepQ(
        model,
        in_key,
        mask_key,
        pre,
        lr=float(a.lr),
        gamma=float(a.gamma),
        tau=float(a.tau),
        double=bool(a.double),
        buffer_size=int(a.buffer_size),
        batch_size=int(a.batch_size),
        seed=component_seed(cfg.seed, "replay"),
    )


def make_deep_tamer(
    cfg: DictConfig, model: torch.nn.Module, inputs: Callable[[TensorDictBase], torch.Tensor], boards: int
) -> DeepTamer:
    """Deep TAMER (``human=mlp``): the network ``model`` over ``inputs``, shared by ``boards`` boards."""
    h = cfg.human
    return DeepTamer(
        model,
        inputs,
        boards,
        lr=float(h.lr),
        credit=make_credit(cfg),
        window=float(h.window),
        renormalise=bool(h.renormalise),
        history=int(h.history),
        buffer_size=int(h.buffer_size),
        batch_size=int(h.batch_size),
        replay_every=int(h.replay_every),
        seed=component_seed(cfg.seed, "human_model"),
    )


def make_shared_tile_tamer(cfg: DictConfig, config: KeepawayConfig, fields: int) -> SharedTileTamer:
    """The tile-coded keepaway H^ (``human=tile_coded``) of one learner, shared by its ``fields``."""
    model = TileCoding(
        keepaway_tile_widths(config.keepers, config.takers), num_actions=config.num_actions, learners=1
    )
    return SharedTileTamer(keeper_tamer_on(cfg, model, fields))


# ------------------------------------------------------------------------------- gym


def make_gym_task(cfg: DictConfig) -> GymTask:
    """The task of ``domain=gym``: ``domain.make``'s callable, else ``domain.env_id`` (``ConfigError`` if the
    callable does not import)."""
    d = cfg.domain
    steps = OmegaConf.select(cfg, "domain.max_episode_steps")
    make = OmegaConf.select(cfg, "domain.make")
    if make is not None:
        return GymTask(make=load_callable(make, "domain.make"))
    return GymTask(env_id=str(d.env_id), max_episode_steps=None if steps is None else int(steps))


def names_a_checkpoint(reference: object) -> bool:
    """Whether ``trainer.reference`` names a run directory or checkpoint file rather than a
    ``module:callable`` (which holds no path separator and does not end in ``.pt``)."""
    text = str(reference)
    return Path(text).exists() or "/" in text or os.sep in text or text.endswith(".pt")


class PolicyReference:
    """A saved ``domain=gym`` policy as the oracle's reference: its greedy action of each observation [B, S].

    :param checkpoint: as ``load_checkpoint`` returns it (a run of any agent on ``domain=gym``).
    """

    def __init__(self, checkpoint: dict[str, Any]) -> None:
        self.module, info = load_policy(checkpoint)
        self.path, self.describe = str(checkpoint["path"]), str(info["describe"])
        self.observation_size, self.actions = int(info["observation_size"]), int(info["actions"])

    @torch.no_grad()
    def __call__(self, obs: torch.Tensor) -> torch.Tensor:
        td = TensorDict({keys.OBSERVATION: obs.to(torch.float32)}, batch_size=obs.shape[:1])
        return self.module(td).get(keys.ACTION).reshape(-1).to(torch.int64)

    @torch.no_grad()
    def values(self, obs: torch.Tensor) -> torch.Tensor:
        """The action values [B, A] the policy acts on: fused Q and H^ where it was taught, else Q (a TAMER
        run's: H^)."""
        td = self.module(TensorDict({keys.OBSERVATION: obs.to(torch.float32)}, batch_size=obs.shape[:1]))
        for key in (keys.FUSED_VALUES, keys.ENV_VALUES, keys.HUMAN_VALUES):
            found = td.get(key, None)
            if found is not None:
                return found.to(torch.float64)
        raise ValueError(f"the saved policy {self.path} writes no action values")


def make_gym_reference(cfg: DictConfig) -> Reference:
    """The reference policy ``trainer.reference`` names (observations [B, S] -> actions or action values): a
    ``module:callable``, or a ``domain=gym`` run directory or checkpoint whose greedy policy it is
    (``CheckpointError`` naming the file if it is none)."""
    reference = cfg.trainer.reference
    if names_a_checkpoint(reference):
        return PolicyReference(load_checkpoint(str(reference), domain="gym"))
    return load_callable(reference, "trainer.reference")


def values_of(reference: Reference) -> Callable[[torch.Tensor], object]:
    """What the value proxy reads of a reference :func:`make_gym_reference` made: a saved policy's action
    values (:meth:`PolicyReference.values`), or the user's callable itself."""
    return reference.values if isinstance(reference, PolicyReference) else reference


def make_gym_trainer(cfg: DictConfig, actions: int, log: FeedbackLog | None) -> Trainer:
    """The trainer of ``domain=gym``: a replayed log, the value proxy on ``trainer.reference``'s action
    values, or the simulated oracle against ``trainer.reference``, with ``trainer.timing``."""
    t = cfg.trainer
    if t.name == "replay":
        return make_replay(cfg, log)
    if t.name == "value_proxy":
        proxy = ReferenceValueProxy(values_of(make_gym_reference(cfg)), actions, t.mode, t.scale, t.reaction)
        return with_timing(cfg, proxy, log)
    base = ReferenceOracle(
        make_gym_reference(cfg),
        actions,
        frequency=t.frequency,
        consistency=t.consistency,
        seed=component_seed(cfg.seed, "trainer"),
        reaction=t.reaction,
    )
    return with_timing(cfg, base, log)
