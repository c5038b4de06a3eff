"""``make_*`` factories from the Hydra config, each checking its own section first.

Every bad value raises :class:`ConfigError` naming the value and what is allowed,
before any work starts.
"""

from __future__ import annotations

import re

import numba
import torch
from omegaconf import DictConfig, OmegaConf

from hfrl_torch.agents.cem import CEMConfig
from hfrl_torch.agents.cem.cem import NOISE_SCHEDULES, Rollout
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.logger import BACKENDS, Logger, make_logger
from hfrl_torch.common.validation import require_bool, require_choice, require_float, require_int
from hfrl_torch.envs.tetris.env import ENGINES, TetrisEnv
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.feedback.credit import CreditModel, GammaDelay, PreviousStep, UniformDelay
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.schedules import AnnealedWeight, ConstantWeight, TrustWeight, WeightSchedule
from hfrl_torch.fusion.schemes import FUSIONS

DOMAINS = ("tetris", "keepaway")
AGENTS = ("cem", "tamer", "qlearning", "pg", "sarsa")
TRAINERS = ("none", "oracle", "value_proxy", "replay", "interactive")
CREDITS = ("previous_step", "gamma", "uniform")
FEATURE_SETS = ("bt", "knox", "dellacherie", "dt")


def make_device(cfg: DictConfig) -> torch.device:
    """The torch device named by ``device`` (``cpu``, ``cuda``, ``cuda:N``)."""
    name = cfg.device
    if not isinstance(name, str) or not re.fullmatch(r"cpu|cuda(:\d+)?", name):
        raise ConfigError(f"device={name!r} is invalid; allowed: cpu, cuda, cuda:N")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={name!r} was asked for but no CUDA device is available; use device=cpu")
    return torch.device(name)


def set_threads(cfg: DictConfig) -> int:
    """Apply ``threads`` to torch and numba (the engines' games run in parallel over threads)."""
    n = require_int(cfg, "threads", 1, 256)
    n = min(n, numba.config.NUMBA_NUM_THREADS)
    numba.set_num_threads(n)
    torch.set_num_threads(n)  # last: numba's OpenMP layer can reset torch's thread count
    return n


def make_rules(cfg: DictConfig) -> TetrisRules:
    """Tetris rules from ``domain``."""
    require_choice(cfg, "domain.name", ("tetris",))
    return TetrisRules(
        width=require_int(cfg, "domain.width", 4, 30),
        height=require_int(cfg, "domain.height", 4, 1000),
        bag=require_bool(cfg, "domain.bag"),
        spawn_topout=require_bool(cfg, "domain.spawn_topout"),
        preview=require_bool(cfg, "domain.preview"),
    )


def check_domain(cfg: DictConfig) -> None:
    """Check the domain's non-rule settings."""
    require_choice(cfg, "domain.features", FEATURE_SETS)
    require_choice(cfg, "domain.engine", ENGINES)
    require_int(cfg, "domain.max_pieces", 0)


def make_env(cfg: DictConfig, batch: int) -> TetrisEnv:
    """A batched ``TetrisEnv`` from ``domain`` and ``device``."""
    check_domain(cfg)
    return TetrisEnv(
        batch=batch,
        rules=make_rules(cfg),
        features=cfg.domain.features,
        engine=cfg.domain.engine,
        max_pieces=cfg.domain.max_pieces,
        device=make_device(cfg),
        seed=cfg.seed,
    )


def make_rollout(cfg: DictConfig, features: str | None = None, random_policy: bool = False) -> Rollout:
    """Whole-game rollouts of linear policies (or uniformly random placements) on the configured
    engine (numba on CPU)."""
    check_domain(cfg)
    rules = make_rules(cfg)
    fid = feature_id(features or cfg.domain.features)
    device = make_device(cfg)
    engine = cfg.domain.engine
    if engine == "auto":
        engine = "numba" if device.type == "cpu" else "torch"
    max_pieces = cfg.domain.max_pieces

    if engine == "numba":
        if device.type != "cpu":
            raise ConfigError(f"domain.engine='numba' runs on the CPU only, not on device={device}")
        from hfrl_torch.envs.tetris.engine_numba import play
    else:
        from hfrl_torch.envs.tetris import engine_torch

        def play(*args, **kwargs):
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
    require_choice(cfg, "agent.name", ("cem",))
    require_int(cfg, "agent.iterations", 1)
    return CEMConfig(
        population=require_int(cfg, "agent.population", 2),
        elite_fraction=require_float(cfg, "agent.elite_fraction", 0.001, 1.0),
        initial_mean=require_float(cfg, "agent.initial_mean"),
        initial_variance=require_float(cfg, "agent.initial_variance", 0.0),
        noise=require_choice(cfg, "agent.noise", NOISE_SCHEDULES),
        noise_value=require_float(cfg, "agent.noise_value", 0.0),
        noise_start=require_float(cfg, "agent.noise_start", 0.0),
        noise_decay=require_float(cfg, "agent.noise_decay", 1e-9),
        games_per_candidate=require_int(cfg, "agent.games_per_candidate", 1),
        eval_games=require_int(cfg, "agent.eval_games", 1),
    )


def make_credit(cfg: DictConfig) -> CreditModel:
    """H^'s credit assignment from ``human.credit``."""
    name = require_choice(cfg, "human.credit", CREDITS)
    if name == "previous_step":
        return PreviousStep()
    if name == "gamma":
        return GammaDelay(
            require_float(cfg, "human.gamma_shape", 1e-6), require_float(cfg, "human.gamma_scale", 1e-6)
        )
    low = require_float(cfg, "human.uniform_low", 0.0)
    return UniformDelay(low, require_float(cfg, "human.uniform_high", low + 1e-6))


def check_human(cfg: DictConfig, model: str = "linear") -> None:
    """Check ``human``, the settings of H^ (TAMER's model of the feedback): ``linear`` on Tetris
    features, or ``tile_coded`` on the keepaway keepers' tiles."""
    require_choice(cfg, "human.name", (model,))
    require_float(cfg, "human.alpha", 1e-12)
    if model == "linear":
        require_choice(cfg, "human.features", ("knox", "bt"))
    else:
        require_choice(cfg, "human.model", ("team", "keeper"))
    make_credit(cfg)
    require_float(cfg, "human.window", 1e-6)
    require_bool(cfg, "human.renormalise")
    if model == "linear":
        require_float(cfg, "human.seconds_per_placement", 1e-6)
    else:
        require_int(cfg, "human.history", 1, 1024)


def check_tamer(cfg: DictConfig) -> None:
    """Check ``agent`` for TAMER, and ``human``."""
    require_int(cfg, "agent.games", 1)
    require_int(cfg, "agent.learners", 1, 100_000)
    check_human(cfg)


def make_weight_schedule(cfg: DictConfig, learners: int = 1) -> WeightSchedule:
    """The weight on H^ of ``fusion`` for each of ``learners``: the trust factor (eq. 4.4), annealed
    (Knox & Stone) or fixed."""
    name = require_choice(cfg, "fusion.name", FUSIONS)
    if name in ("none", "human_only"):
        return ConstantWeight([0.0] * learners)
    if name == "annealed":
        w0 = require_float(cfg, "fusion.weight", 0.0)
        return AnnealedWeight([w0] * learners, require_float(cfg, "fusion.factor", 1e-9, 1.0))
    weight = OmegaConf.select(cfg, "fusion.weight")
    if weight == "trust":
        return TrustWeight.from_initial(require_float(cfg, "fusion.initial_trust", 0.0), learners)
    if isinstance(weight, str):
        raise ConfigError(f"fusion.weight={weight!r} is invalid; allowed: trust, or a number >= 0")
    return ConstantWeight([require_float(cfg, "fusion.weight", 0.0)] * learners)


def fusion_normalises(cfg: DictConfig) -> bool:
    """Whether Tetris fusion rescales R and H^ to [0, 1] per decision: ``fusion.normalise`` (null: yes, CE
    values are hundreds of times H^); false when the scheme has no such key. Keepaway reads the same key
    its own way (``keepaway_sarsa.fusion_scaling``)."""
    if "normalise" not in cfg.fusion or OmegaConf.select(cfg, "fusion.normalise") is None:
        return "normalise" in cfg.fusion
    return require_bool(cfg, "fusion.normalise")


def make_trainer(cfg: DictConfig, log: FeedbackLog | None):
    """The simulated trainer (or replay) of ``trainer``, logging every event it gives to ``log``."""
    from hfrl_torch.trainers import HumanLikeTiming, OracleTrainer, ReplayTrainer, ValueProxyTrainer

    name = require_choice(cfg, "trainer.name", TRAINERS)
    if name == "none":
        return None
    reaction = require_float(cfg, "trainer.reaction", 1e-6)
    if OmegaConf.select(cfg, "trainer.reference") not in (None, "dellacherie"):
        raise ConfigError(
            f"trainer.reference={cfg.trainer.reference!r} is invalid for Tetris; allowed: null "
            "(Dellacherie's weights; learned references are a keepaway option)"
        )
    if name == "oracle":
        base = OracleTrainer(
            frequency=require_float(cfg, "trainer.frequency", 0.0, 1.0),
            consistency=require_float(cfg, "trainer.consistency", 0.0, 1.0),
            seed=int(cfg.seed) * 2 + 1,
            reaction=reaction,
        )
    elif name == "value_proxy":
        base = ValueProxyTrainer(
            mode=require_choice(cfg, "trainer.mode", ("sign", "scaled")),
            scale=require_float(cfg, "trainer.scale", 1e-12),
            reaction=reaction,
        )
    else:
        path = OmegaConf.select(cfg, "trainer.log")
        if not path:
            raise ConfigError("trainer=replay needs trainer.log=<feedback log file>")
        base = ReplayTrainer.from_log(path, reaction=reaction)
    if not require_bool(cfg, "trainer.timing.enabled"):
        base.log = log
        return base
    fatigue = OmegaConf.select(cfg, "trainer.timing.fatigue_tau")
    tail = OmegaConf.select(cfg, "trainer.timing.tail_lines")
    return HumanLikeTiming(
        base,
        delay=GammaDelay(
            require_float(cfg, "trainer.timing.delay_shape", 1e-6),
            require_float(cfg, "trainer.timing.delay_scale", 1e-6),
        ),
        fatigue_tau=None if fatigue is None else require_float(cfg, "trainer.timing.fatigue_tau", 1e-6),
        positive_bias=require_float(cfg, "trainer.timing.positive_bias", 0.0, 1.0),
        absence=require_float(cfg, "trainer.timing.absence", 0.0, 1.0),
        tail_lines=None if tail is None else require_float(cfg, "trainer.timing.tail_lines", 1e-6),
        seed=int(cfg.seed) * 2 + 2,
        log=log,
    )


def check_run(cfg: DictConfig) -> None:
    """Check the top-level and the not-yet-implemented groups."""
    require_int(cfg, "seed", 0, 2**62)
    require_choice(cfg, "agent.name", AGENTS)
    require_choice(cfg, "fusion.name", FUSIONS)
    require_choice(cfg, "trainer.name", TRAINERS)
    require_choice(cfg, "logger.backend", BACKENDS)
    make_device(cfg)


def make_run_logger(cfg: DictConfig, log_dir: str, purge_step: int | None) -> Logger:
    """The logger of ``logger.backend`` writing under ``log_dir``."""
    return make_logger(cfg.logger.backend, log_dir, purge_step=purge_step)


def validate_train_config(cfg: DictConfig) -> None:
    """Check every section ``train.py`` uses, before any work or output."""
    domain = require_choice(cfg, "domain.name", DOMAINS)
    check_run(cfg)
    if domain == "keepaway" or cfg.agent.name == "sarsa":
        from hfrl_torch.experiment.keepaway_sarsa import check_keepaway_feedback, check_sarsa

        if domain != "keepaway" or cfg.agent.name != "sarsa":
            raise ConfigError(
                f"domain={domain} agent={cfg.agent.name}: keepaway is learned by agent=sarsa, "
                "and agent=sarsa learns keepaway only (domain=keepaway agent=sarsa)"
            )
        require_int(cfg, "threads", 1, 256)
        check_sarsa(cfg)
        check_keepaway_feedback(cfg)
        return
    make_rules(cfg)
    check_domain(cfg)
    require_int(cfg, "threads", 1, 256)
    agent = require_choice(cfg, "agent.name", AGENTS)
    trainer = cfg.trainer.name
    fusion = cfg.fusion.name
    if agent == "cem":
        make_cem_config(cfg)
        make_weight_schedule(cfg)
        fusion_normalises(cfg)
        if fusion != "none" and trainer == "none":
            raise ConfigError(
                f"fusion={fusion!r} fuses the trainer's H^ with the environment; choose a trainer: "
                "oracle, value_proxy, replay (or fusion=none)"
            )
        if trainer == "interactive":
            from hfrl_torch.interactive.live import check_interactive

            check_interactive(cfg)
        if trainer != "none":
            check_human(cfg)
            require_int(cfg, "agent.watch_pieces", 1)
            if cfg.domain.features != "bt":
                raise ConfigError(
                    f"domain.features={cfg.domain.features!r} with a trainer: CE + human feedback "
                    "fuses over the bt features (a prefix of H^'s knox set); allowed: bt"
                )
    elif agent == "qlearning":
        from hfrl_torch.experiment.tetris_qlearning import check_qlearning

        check_qlearning(cfg)
    elif agent == "pg":
        from hfrl_torch.experiment.tetris_pg import check_pg

        check_pg(cfg)
    else:
        check_tamer(cfg)
        if fusion != "none":
            raise ConfigError(
                f"fusion={fusion!r} with agent=tamer: TAMER acts on H^ alone; use fusion=none, "
                "or agent=cem fusion=human_only to run H^ inside the combined learner"
            )
        if trainer == "none":
            raise ConfigError(
                "agent=tamer learns only from feedback; choose a trainer: oracle, value_proxy, replay"
            )
        if trainer == "interactive":
            raise ConfigError(
                "trainer=interactive teaches the combined learner: use agent=cem (fusion=linear by default), "
                "which keeps learning from the game when you leave"
            )
    if trainer == "replay" and not OmegaConf.select(cfg, "trainer.log"):
        raise ConfigError("trainer=replay needs trainer.log=<feedback log file>")
