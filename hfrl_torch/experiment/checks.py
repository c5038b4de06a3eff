"""The checks of a run's config groups, each raising ``ConfigError`` with one line naming the bad value and
what is allowed: the domains' (``check_tetris_domain``, ``check_keepaway_domain``, ``check_gym_domain``),
each learner's (which its class names as ``Learner.check``), and the parts they share (H^, trainers, fusion,
kernels).
``config.validate_train`` runs them through the registry; the ``make_*`` factories then check nothing.
"""

from __future__ import annotations

import math
import re
from collections.abc import Collection, Mapping, Sequence
from dataclasses import fields
from pathlib import Path

import gymnasium as gym
import torch
from omegaconf import DictConfig, OmegaConf

from hfrl_torch.agents.cem.cem import NOISE_SCHEDULES
from hfrl_torch.agents.cem.fused_rollout import CANDIDATE_RANKINGS
from hfrl_torch.agents.sarsa.keepers import LEARNER_KERNELS
from hfrl_torch.agents.sarsa.sarsa import trace_capacity
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import CheckpointError, ConfigError
from hfrl_torch.common.validation import require_bool, require_choice, require_float, require_int
from hfrl_torch.envs.gym_task import TaskSpaces, first_frame, task_spaces
from hfrl_torch.envs.keepaway.params import (
    DECISION_TIMINGS,
    HOLD_RULES,
    KERNELS,
    PERCEPTIONS,
    PRESETS,
    KeepawayConfig,
)
from hfrl_torch.envs.tetris.env import ENGINES
from hfrl_torch.envs.tetris.features import FEATURE_SETS
from hfrl_torch.experiment.factories import PolicyReference, make_gym_reference, make_gym_task, values_of
from hfrl_torch.feedback.credit import CREDITS
from hfrl_torch.feedback.log import read_feedback_log
from hfrl_torch.fusion.schemes import FUSIONS
from hfrl_torch.fusion.weights import UNWEIGHTED, check_weight
from hfrl_torch.interactive.live import KEY_NAMES
from hfrl_torch.interactive.messages import MAX_SPEED, MIN_SPEED
from hfrl_torch.interactive.timeline import MAX_REACTION_S, MIN_REACTION_S
from hfrl_torch.models.tile_coding import MAX_SIZE
from hfrl_torch.trainers.departure import LEAVE_UNITS
from hfrl_torch.trainers.reference_oracle import right_actions
from hfrl_torch.trainers.reference_value_proxy import action_values

TRAINERS = ("none", "oracle", "value_proxy", "replay", "interactive")
KEEPAWAY_TRAINERS = ("none", "oracle", "replay", "interactive")
PG_FUSIONS = ("none", "linear", "annealed")
PPO_REFUSED = {  # the fusion schemes PPO cannot take, and why (learners/gym_ppo.py's docstring)
    "exponential": "it scales R by a factor of H^ and assumes R >= 0, and a logit has no sign of its own",
    "human_only": "on-policy PPO cannot learn from actions H^ alone chooses (agent=dqn fusion=human_only is "
    "Deep TAMER alone)",
}
NORMALISE = ("true", "false", "spread", "null")
MAX_TABLE_GIB = 16.0  # refuse configs whose keepaway weight tables alone would need more memory than this


# ------------------------------------------------------------------------------ run


def check_threads(cfg: DictConfig) -> None:
    """``threads``: ``auto`` (every core this process may use) or a count of threads."""
    value = cfg.threads
    ok = value == "auto" or (isinstance(value, int) and not isinstance(value, bool) and 1 <= value <= 256)
    if not ok:
        raise ConfigError(f"threads={value!r} is invalid: must be auto or an integer in 1..256")


def check_device(cfg: DictConfig) -> str:
    """``device``: ``cpu``, ``cuda`` or ``cuda:N``, and CUDA only where there is a GPU."""
    name = OmegaConf.select(cfg, "device", default="cpu")
    if not isinstance(name, str) or not re.fullmatch(r"cpu|cuda(:\d+)?", name):
        raise ConfigError(f"device={name!r} is invalid; allowed: cpu, cuda, cuda:N")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device={name!r} was asked for but no CUDA device is available; use device=cpu")
    return name


# ---------------------------------------------------------------------------- tetris


def check_tetris_domain(cfg: DictConfig) -> None:
    """The board, the rules and the engine."""
    require_int(cfg, "domain.width", 4, 30)
    require_int(cfg, "domain.height", 4, 1000)
    for flag in ("bag", "spawn_topout", "preview"):
        require_bool(cfg, f"domain.{flag}")
    require_choice(cfg, "domain.features", FEATURE_SETS)
    require_choice(cfg, "domain.engine", ENGINES)
    require_int(cfg, "domain.max_pieces", 0)
    if cfg.domain.engine == "numba" and str(OmegaConf.select(cfg, "device", default="cpu")) != "cpu":
        raise ConfigError(f"domain.engine='numba' runs on the CPU only, not on device={cfg.device}")


def check_tetris_evaluation(cfg: DictConfig) -> None:
    """``evaluate.py`` on Tetris: the number of games and the board."""
    require_int(cfg, "games", 1)
    check_tetris_domain(cfg)


def check_cem(cfg: DictConfig) -> None:
    """The cross-entropy method, and the combined learner when a trainer teaches it."""
    require_int(cfg, "agent.iterations", 1)
    require_int(cfg, "agent.population", 2)
    require_float(cfg, "agent.elite_fraction", 0.001, 1.0)
    require_float(cfg, "agent.initial_mean")
    require_float(cfg, "agent.initial_variance", 0.0)
    require_choice(cfg, "agent.noise", NOISE_SCHEDULES)
    require_float(cfg, "agent.noise_value", 0.0)
    require_float(cfg, "agent.noise_start", 0.0)
    require_float(cfg, "agent.noise_decay", 1e-9)
    require_int(cfg, "agent.games_per_candidate", 1)
    require_int(cfg, "agent.eval_games", 1)
    fusion, trainer = cfg.fusion.name, cfg.trainer.name
    if fusion != "none" and trainer == "none":
        raise ConfigError(
            f"fusion={fusion!r} fuses the trainer's H^ with the environment; choose a trainer: "
            "oracle, value_proxy, replay (or fusion=none)"
        )
    if trainer == "none":
        return
    check_human(cfg, "linear")
    require_int(cfg, "agent.watch_pieces", 1)
    candidate_ranking(cfg)
    if cfg.domain.features != "bt":
        raise ConfigError(
            f"domain.features={cfg.domain.features!r} with a trainer: CE + human feedback "
            "fuses over the bt features (a prefix of H^'s knox set); allowed: bt"
        )
    check_tetris_trainer(cfg)


def candidate_ranking(cfg: DictConfig) -> str:
    """When CE + a trainer ranks its candidates fused with H^ (``agent.rank_candidates``, checked); a saved
    run's config from before it says ``agent.alone_after_departure``: fused while teaching, or always."""
    if "rank_candidates" in cfg.agent:
        return require_choice(cfg, "agent.rank_candidates", CANDIDATE_RANKINGS)
    if "alone_after_departure" in cfg.agent and require_bool(cfg, "agent.alone_after_departure"):
        return "fused_while_teaching"
    return "fused"


def check_tamer(cfg: DictConfig) -> None:
    """TAMER: its learners, H^ and the trainer it cannot do without."""
    require_int(cfg, "agent.games", 1)
    require_int(cfg, "agent.learners", 1, 100_000)
    check_human(cfg, "linear")
    fusion, trainer = cfg.fusion.name, cfg.trainer.name
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
    check_tetris_trainer(cfg)


def check_qlearning(cfg: DictConfig) -> None:
    """Q-learning, which learns from the environment's reward alone."""
    require_int(cfg, "agent.games", 1)
    require_int(cfg, "agent.learners", 1, 100_000)
    require_float(cfg, "agent.alpha", 1e-12)
    require_float(cfg, "agent.gamma", 0.0, 1.0)
    require_float(cfg, "agent.epsilon", 0.0, 1.0)
    require_float(cfg, "agent.epsilon_decay", 0.0, 1.0)
    require_float(cfg, "agent.epsilon_min", 0.0, 1.0)
    require_choice(cfg, "agent.features", FEATURE_SETS)
    require_int(cfg, "agent.eval_games", 0)
    for group in ("trainer", "fusion"):
        name = OmegaConf.select(cfg, f"{group}.name")
        if name != "none":
            raise ConfigError(
                f"{group}={name!r} with agent={cfg.agent.name}: this learner uses the environment's reward "
                f"alone (no human feedback yet); use {group}=none"
            )


def check_pg(cfg: DictConfig) -> None:
    """Policy gradient, alone or with a trainer's H^ biasing its softmax."""
    require_int(cfg, "agent.games", 1)
    require_int(cfg, "agent.learners", 1, 100_000)
    require_float(cfg, "agent.lr", 1e-12)
    natural = require_bool(cfg, "agent.natural")
    require_float(cfg, "agent.damping", 1e-12 if natural else 0.0)
    require_float(cfg, "agent.temperature", 1e-6)
    require_int(cfg, "agent.games_per_update", 1)
    require_float(cfg, "agent.baseline_decay", 0.0, 1.0)
    require_choice(cfg, "agent.features", FEATURE_SETS)
    require_int(cfg, "agent.eval_games", 0)
    fusion, trainer = cfg.fusion.name, cfg.trainer.name
    if trainer == "none":
        if fusion != "none":
            raise ConfigError(
                f"fusion={fusion!r} fuses a trainer's H^ into the policy; choose a trainer: oracle, ..."
            )
        return
    if fusion not in PG_FUSIONS:
        raise ConfigError(
            f"fusion={fusion!r} with agent=pg is invalid; allowed: {', '.join(PG_FUSIONS)} (H^ biases the "
            "softmax policy: pi ~ exp((theta . f + w H^) / T))"
        )
    if trainer == "interactive":
        raise ConfigError(
            "trainer=interactive teaches agent=cem; agent=pg takes a simulated trainer or replay"
        )
    if cfg.agent.features != "bt" or cfg.human.features != "knox":
        raise ConfigError(
            "agent=pg with a trainer needs agent.features=bt and human.features=knox (bt is its prefix)"
        )
    check_human(cfg, "linear")
    check_tetris_trainer(cfg)


def check_tetris_trainer(cfg: DictConfig) -> None:
    """The Tetris trainer: a simulated one (oracle, value proxy, human-like timing), a replay or a person."""
    name = require_choice(cfg, "trainer.name", TRAINERS)
    if name == "none":
        return
    if name == "interactive":
        check_interactive(cfg)
        return
    require_float(cfg, "trainer.reaction", 1e-6)
    check_departure(cfg)
    if OmegaConf.select(cfg, "trainer.reference") not in (None, "dellacherie"):
        raise ConfigError(
            f"trainer.reference={cfg.trainer.reference!r} is invalid for Tetris; allowed: null "
            "(Dellacherie's weights; learned references are a keepaway option)"
        )
    if name == "oracle":
        require_float(cfg, "trainer.frequency", 0.0, 1.0)
        require_float(cfg, "trainer.consistency", 0.0, 1.0)
    elif name == "value_proxy":
        require_choice(cfg, "trainer.mode", ("sign", "scaled"))
        require_float(cfg, "trainer.scale", 1e-12)
    else:
        check_replay_log(cfg)
    if require_bool(cfg, "trainer.timing.enabled"):
        check_timing(cfg, tetris=True)


def check_departure(cfg: DictConfig) -> None:
    """``trainer.leave_after`` (null, or episodes or simulated minutes >= 0) and ``trainer.leave_unit``."""
    if OmegaConf.select(cfg, "trainer.leave_after") is not None:
        require_float(cfg, "trainer.leave_after", 0.0)
    if "leave_unit" in cfg.trainer:
        require_choice(cfg, "trainer.leave_unit", LEAVE_UNITS)


def check_timing(cfg: DictConfig, tetris: bool) -> None:
    """``trainer.timing``: the simulated trainer's human-like reaction delays, fatigue, bias and absences."""
    require_float(cfg, "trainer.timing.delay_shape", 1e-6)
    require_float(cfg, "trainer.timing.delay_scale", 1e-6)
    if OmegaConf.select(cfg, "trainer.timing.fatigue_tau") is not None:
        require_float(cfg, "trainer.timing.fatigue_tau", 1e-6)
    require_float(cfg, "trainer.timing.positive_bias", 0.0, 1.0)
    require_float(cfg, "trainer.timing.absence", 0.0, 1.0)
    if OmegaConf.select(cfg, "trainer.timing.tail_lines") is not None:
        if not tetris:
            raise ConfigError(
                "trainer.timing.tail_lines is a Tetris option (lines per game); keepaway allows only null"
            )
        require_float(cfg, "trainer.timing.tail_lines", 1e-6)


def check_replay_log(cfg: DictConfig) -> None:
    """``trainer.log``: the feedback log a replay gives again, which must exist and read whole (a corrupt or
    cut line is refused here, before the run directory exists, rather than replayed in part)."""
    path = OmegaConf.select(cfg, "trainer.log")
    if not path:
        raise ConfigError("trainer=replay needs trainer.log=<feedback log file>")
    if not Path(str(path)).is_file():
        raise ConfigError(f"trainer.log={str(path)!r} is not a file; give a feedback log (feedback.jsonl)")
    error = read_feedback_log(str(path)).error
    if error is not None:
        raise ConfigError(f"trainer.log={str(path)!r} cannot be replayed: {_first(error)}")


def check_human(cfg: DictConfig, model: str) -> None:
    """``human``, the settings of H^ (TAMER's model of the feedback): ``linear`` on Tetris features, or
    ``tile_coded`` on the keepaway keepers' tiles."""
    require_choice(cfg, "human.name", (model,))
    require_float(cfg, "human.alpha", 1e-12)
    if model == "linear":
        require_choice(cfg, "human.features", ("knox", "bt"))
    else:
        require_choice(cfg, "human.model", ("team", "keeper"))
    name = require_choice(cfg, "human.credit", CREDITS)
    if name == "gamma":
        require_float(cfg, "human.gamma_shape", 1e-6)
        require_float(cfg, "human.gamma_scale", 1e-6)
    elif name == "uniform":
        low = require_float(cfg, "human.uniform_low", 0.0)
        require_float(cfg, "human.uniform_high", low + 1e-6)
    require_float(cfg, "human.window", 1e-6)
    require_bool(cfg, "human.renormalise")
    if model == "linear":
        require_float(cfg, "human.seconds_per_placement", 1e-6)
    else:
        require_int(cfg, "human.history", 1, 1024)


def check_fusion(
    cfg: DictConfig,
    evidence: Collection[str] = (),
    givers: Mapping[str, Sequence[str]] | None = None,
    spread: bool = False,
) -> None:
    """``fusion``: the scheme, its weight (checked by the weight's kind for a learner that gives
    ``evidence``; ``givers``: the agents that give each kind, for the error), the scale (``spread``: the
    domain has a Q spread to scale H^ by)."""
    name = require_choice(cfg, "fusion.name", FUSIONS)
    check_weight(cfg, evidence, givers)
    if name in UNWEIGHTED:
        return
    if "normalise" in cfg.fusion:
        value = OmegaConf.select(cfg, "fusion.normalise")
        if not (value is None or isinstance(value, bool) or value == "spread"):
            raise ConfigError(f"fusion.normalise={value!r} is invalid; allowed: {', '.join(NORMALISE)}")
        if value == "spread" and not spread:
            raise ConfigError(
                f"fusion.normalise='spread' is not an option of domain={cfg.domain.name}; "
                "allowed here: true, false, null"
            )


def check_interactive(cfg: DictConfig) -> None:
    """``trainer`` for ``trainer=interactive``: the page's server, speed and keys."""
    host = OmegaConf.select(cfg, "trainer.host")
    if not isinstance(host, str) or not host:
        raise ConfigError(f"trainer.host={host!r} is invalid: must be an address such as 127.0.0.1")
    require_int(cfg, "trainer.port", 0, 65535)
    if OmegaConf.select(cfg, "trainer.actions_per_s") is not None:
        require_float(cfg, "trainer.actions_per_s", MIN_SPEED, MAX_SPEED)
    require_float(cfg, "trainer.wait_for_page_s", 0.0)
    require_float(cfg, "trainer.reconnect_wait_s", 0.0)
    if OmegaConf.select(cfg, "trainer.reaction_s") is not None:  # runs saved before it existed: 0.3
        require_float(cfg, "trainer.reaction_s", MIN_REACTION_S, MAX_REACTION_S)
    if OmegaConf.select(cfg, "trainer.blind") is not None:  # runs saved before it existed: not blind
        require_bool(cfg, "trainer.blind")
    require_int(cfg, "trainer.max_message_bytes", 64, 65536)
    require_float(cfg, "trainer.max_messages_per_s", 1.0, 1000.0)
    teachers = require_int(cfg, "trainer.max_teachers", 1, 64)
    pages = require_int(cfg, "trainer.max_connections", 1, 64)
    if teachers > pages:
        raise ConfigError(
            f"trainer.max_teachers={teachers} is invalid: must be at most trainer.max_connections={pages}"
        )
    token = OmegaConf.select(cfg, "trainer.token")
    if token is not None and (not isinstance(token, str) or len(token) < 8):
        raise ConfigError("trainer.token is invalid: must be null (generated) or a string of 8+ characters")
    chosen = [OmegaConf.select(cfg, f"trainer.keys.{k}") for k in KEY_NAMES]
    for name, key in zip(KEY_NAMES, chosen, strict=True):
        if not isinstance(key, str) or len(key) != 1:
            raise ConfigError(f"trainer.keys.{name}={key!r} is invalid: must be one character")
    if len(set(chosen)) != len(chosen):
        raise ConfigError(
            f"trainer.keys {dict(zip(KEY_NAMES, chosen, strict=True))} must be four different keys"
        )


# -------------------------------------------------------------------------- keepaway


def check_keepaway_domain(cfg: DictConfig) -> None:
    """The keepaway task (``KeepawayConfig``'s fields) and how it runs."""
    cfg.domain.preset = str(cfg.domain.preset)  # the command line reads preset=2005 as a number
    require_choice(cfg, "domain.preset", PRESETS)
    require_int(cfg, "domain.keepers", 2, 11)
    require_int(cfg, "domain.takers", 1, 11)
    require_float(cfg, "domain.length", 1.0, 200.0)
    require_float(cfg, "domain.width", 1.0, 200.0)
    if OmegaConf.select(cfg, "domain.turnover_cycles") is not None:
        require_int(cfg, "domain.turnover_cycles", 1, 100)
    require_bool(cfg, "domain.movement_noise")
    for name, allowed in (
        ("perception", PERCEPTIONS),
        ("hold_ball", HOLD_RULES),
        ("decision_timing", DECISION_TIMINGS),
    ):
        if name in cfg.domain:  # a saved run's config that predates the option plays the exact task's
            require_choice(cfg, f"domain.{name}", allowed)
    if require_bool(cfg, "domain.noisy_observations") and cfg.domain.get("perception") == "server":
        raise ConfigError(
            "domain.noisy_observations=true quantises the exact state's view; domain.perception=server "
            "quantises every player's sightings already: set domain.noisy_observations=false"
        )
    require_int(cfg, "domain.decision_period_cycles", 1, 100)
    require_int(cfg, "domain.intercept_horizon", 1, 200)
    require_int(cfg, "domain.collision_passes", 1, 100)
    check_kernels(cfg)
    names = {f.name for f in fields(KeepawayConfig)}
    unknown = [k for k in cfg.domain if k not in names and k not in ("name", "batch")]
    if unknown:
        raise ConfigError(
            f"domain.{unknown[0]} is not a keepaway option; allowed: {', '.join(sorted(names))}"
        )


def check_keepaway_evaluation(cfg: DictConfig) -> None:
    """``evaluate.py`` on keepaway: episodes, the fields played at once, the episode cap and the task."""
    require_int(cfg, "episodes", 1)
    require_int(cfg, "domain.batch", 1, 65536)
    if OmegaConf.select(cfg, "max_episode_s") is not None:
        require_float(cfg, "max_episode_s", 0.1)
    check_keepaway_domain(cfg)


def check_kernels(cfg: DictConfig) -> str:
    """``domain.kernels``, checked against ``device``."""
    kernels = require_choice(cfg, "domain.kernels", KERNELS)
    device = str(OmegaConf.select(cfg, "device", default="cpu"))
    if kernels in ("numba", "cycle") and device != "cpu":
        raise ConfigError(
            f"domain.kernels={kernels!r} runs on the CPU only, not device={device}; "
            "use domain.kernels=auto or torch"
        )
    return kernels


def check_learner_kernels(cfg: DictConfig) -> str:
    """``agent.kernels`` (the Sarsa learner's path), checked against ``device``."""
    kernels = require_choice(cfg, "agent.kernels", LEARNER_KERNELS)
    device = str(OmegaConf.select(cfg, "device", default="cpu"))
    if kernels == "numba" and device != "cpu":
        raise ConfigError(
            f"agent.kernels={kernels!r} runs on the CPU only, not device={device}; "
            "use agent.kernels=auto or torch"
        )
    return kernels


def check_sarsa(cfg: DictConfig) -> None:
    """The Sarsa keepers, their budget, logging, and the memory their tables need."""
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
    if "greedy_with_bandit" in cfg.agent:  # a saved run's config that predates the option explores
        require_bool(cfg, "agent.greedy_with_bandit")
    lambda_ = require_float(cfg, "agent.lambda", 0.0, 1.0)
    gamma = require_float(cfg, "agent.gamma", 1e-9, 1.0)
    tilings = require_int(cfg, "agent.tilings", 1, 1024)
    bits = require_int(cfg, "agent.table_bits", 1, int(math.log2(MAX_SIZE)))
    min_trace = require_float(cfg, "agent.min_trace", 1e-12, 1.0)
    share = require_bool(cfg, "agent.share_weights")
    if "kernels" in cfg.agent:  # a saved run's config that predates the option decides by auto
        check_learner_kernels(cfg)
    keepers = require_int(cfg, "domain.keepers", 3, 11)
    takers = require_int(cfg, "domain.takers", 2, 11)
    active = tilings * (4 * keepers + 2 * takers - 3)
    max_traces = OmegaConf.select(cfg, "agent.max_traces")
    if max_traces is not None:
        max_traces = require_int(cfg, "agent.max_traces", active, 10_000_000)
    require_float(cfg, "agent.log_minutes", 0.02)  # >= 12 cycles: one TensorBoard step per second
    require_int(cfg, "agent.log_episodes", 1)
    require_float(cfg, "agent.checkpoint_minutes", 0.01)
    tables = learners if share else learners * keepers
    slots = learners * per_learner * keepers  # pending action and traces per field and keeper
    capacity = max_traces if max_traces is not None else trace_capacity(active, gamma * lambda_, min_trace)
    gib = (tables * 2**bits * 4 + slots * capacity * 12) / 2**30
    if gib > MAX_TABLE_GIB:
        raise ConfigError(
            f"agent.learners={learners} x agent.fields_per_learner={per_learner} need {tables} tables of "
            f"2^{bits} weights and {slots} x {capacity} trace slots, {gib:.1f} GiB (limit "
            f"{MAX_TABLE_GIB:.0f}); lower agent.learners, agent.fields_per_learner or agent.table_bits"
        )


def check_keepaway_feedback(cfg: DictConfig) -> None:
    """``fusion``, ``trainer`` and ``human`` for keepers taught by a trainer (thesis Chapter 5)."""
    fusion = cfg.fusion.name
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
        check_interactive(cfg)
        if int(cfg.agent.learners) != 1:
            raise ConfigError(
                f"agent.learners={cfg.agent.learners} with trainer=interactive: one person teaches one team "
                "of keepers on one field; allowed: 1 (the default with trainer=interactive)"
            )
    if int(cfg.agent.fields_per_learner) != 1:
        raise ConfigError(
            f"agent.fields_per_learner={cfg.agent.fields_per_learner} with a trainer: one trainer watches "
            "one field, so each learner plays one field; allowed: 1"
        )
    check_human(cfg, "tile_coded")
    if trainer == "interactive":
        return
    check_departure(cfg)
    if trainer == "replay":
        check_replay_log(cfg)
        return
    reference = OmegaConf.select(cfg, "trainer.reference")
    if reference not in (None, "hand"):
        if not Path(str(reference)).exists():
            raise ConfigError(
                f"trainer.reference={reference!r} is invalid; allowed: null or hand (the hand-coded "
                "keepers), or a keepaway run directory or checkpoint"
            )
        ckpt = load_checkpoint(str(reference), domain="keepaway")
        task = ckpt.get("domain_config", {})
        if (task.get("keepers"), task.get("takers")) != (cfg.domain.keepers, cfg.domain.takers):
            raise ConfigError(
                f"trainer.reference={reference!r} learned {task.get('keepers')}v{task.get('takers')}, "
                f"not {cfg.domain.keepers}v{cfg.domain.takers}"
            )
    require_float(cfg, "trainer.frequency", 0.0, 1.0)
    require_float(cfg, "trainer.consistency", 0.0, 1.0)
    require_float(cfg, "trainer.reaction", 1e-6)
    if require_bool(cfg, "trainer.timing.enabled"):
        check_timing(cfg, tetris=False)


# ------------------------------------------------------------------------- deep learners


def check_dqn(cfg: DictConfig, page: bool = False) -> None:
    """DQN in any domain: its budget, network and exploration, and the trainer's presence (``page``: the
    domain has a browser trainer's page, so ``trainer=interactive`` is allowed)."""
    a = "agent."
    require_int(cfg, a + "frames", 1)
    require_int(cfg, a + "boards", 1, 4096)
    require_int(cfg, a + "steps_per_batch", 1, 10_000)
    require_int(cfg, a + "eval_every", 1)
    require_int(cfg, a + "eval_episodes", 1, 10_000)
    require_int(cfg, a + "learn_after", 0)
    require_float(cfg, a + "frames_per_update", 1e-3)
    require_int(cfg, a + "batch_size", 1, 1_000_000)
    require_int(cfg, a + "buffer_size", 1, 10_000_000)
    require_float(cfg, a + "lr", 1e-12)
    require_float(cfg, a + "gamma", 0.0, 1.0)
    require_float(cfg, a + "tau", 1e-9, 1.0)
    require_bool(cfg, a + "double")
    require_float(cfg, a + "epsilon_start", 0.0, 1.0)
    require_float(cfg, a + "epsilon_end", 0.0, 1.0)
    require_float(cfg, a + "epsilon_frames", 0.0)
    check_cells(cfg, a + "cells")
    fusion, trainer = cfg.fusion.name, cfg.trainer.name
    if trainer == "none" and fusion != "none":
        raise ConfigError(
            f"fusion={fusion!r} fuses a trainer's H^ with the DQN's Q; choose a trainer: oracle, replay "
            "(or fusion=none)"
        )
    if trainer == "interactive" and not page:
        raise ConfigError(
            f"trainer=interactive with agent=dqn on domain={cfg.domain.name}: the browser trainer teaches "
            "agent=cem (Tetris), agent=sarsa (keepaway) and agent=dqn on domain=gym; here agent=dqn takes a "
            "simulated trainer or a replay"
        )


def check_tetris_dqn(cfg: DictConfig) -> None:
    """DQN on Tetris: its features, evaluation cap, and H^ (linear TAMER or Deep TAMER) with the trainer."""
    check_dqn(cfg)
    require_choice(cfg, "agent.features", FEATURE_SETS)
    require_int(cfg, "agent.eval_max_pieces", 1)
    if cfg.trainer.name == "none":
        return
    human = require_choice(cfg, "human.name", ("mlp", "linear"))
    if human == "mlp":
        check_mlp_human(cfg, placements=True)
    else:
        check_human(cfg, human)
    features, q_features = str(cfg.human.features), str(cfg.agent.features)
    if q_features not in (features, "bt") or (q_features == "bt" and features not in ("bt", "knox")):
        raise ConfigError(
            f"agent.features={q_features!r} with human.features={features!r}: the env computes H^'s features "
            "and Q reads their first columns; allowed: agent.features=bt (a prefix of knox) or H^'s own set"
        )
    check_tetris_trainer(cfg)


def check_keepaway_dqn(cfg: DictConfig) -> None:
    """DQN keepers: H^ (tile-coded TAMER or Deep TAMER) and the keepaway trainer."""
    check_dqn(cfg)
    trainer = cfg.trainer.name
    if trainer == "none":
        return
    human = require_choice(cfg, "human.name", ("mlp", "tile_coded"))
    if human == "mlp":
        check_mlp_human(cfg, placements=False)
    else:
        check_human(cfg, human)
    if trainer not in KEEPAWAY_TRAINERS:
        raise ConfigError(f"trainer={trainer} is not available for keepaway; allowed: none, oracle, replay")
    check_keepaway_feedback_trainer(cfg)


def check_cells(cfg: DictConfig, key: str) -> list[int]:
    """A network's hidden layer widths: a list of integers in 1..4096 (an empty list: linear)."""
    cells = OmegaConf.select(cfg, key)
    values = list(cells) if OmegaConf.is_list(cells) else None
    if values is None or not all(
        isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 4096 for v in values
    ):
        raise ConfigError(
            f"{key}={cells!r} is invalid; allowed: a list of layer widths in 1..4096, e.g. [64, 64]"
        )
    return values


def check_mlp_human(cfg: DictConfig, placements: bool) -> None:
    """``human=mlp``: Deep TAMER's network, its Adam step, replay buffer and credit (``placements``: on
    Tetris placements, which also have H^'s feature set and seconds per placement)."""
    h = "human."
    check_cells(cfg, h + "cells")
    require_float(cfg, h + "lr", 1e-12)
    require_int(cfg, h + "batch_size", 1, 1_000_000)
    require_int(cfg, h + "buffer_size", 1, 10_000_000)
    require_int(cfg, h + "replay_every", 1)
    require_int(cfg, h + "history", 1, 1024)
    require_float(cfg, h + "scale", 1e-12)
    name = require_choice(cfg, h + "credit", CREDITS)
    if name == "gamma":
        require_float(cfg, h + "gamma_shape", 1e-6)
        require_float(cfg, h + "gamma_scale", 1e-6)
    elif name == "uniform":
        low = require_float(cfg, h + "uniform_low", 0.0)
        require_float(cfg, h + "uniform_high", low + 1e-6)
    require_float(cfg, h + "window", 1e-6)
    require_bool(cfg, h + "renormalise")
    if placements:
        require_choice(cfg, h + "features", ("knox", "bt"))
        require_float(cfg, h + "seconds_per_placement", 1e-6)


def check_keepaway_feedback_trainer(cfg: DictConfig) -> None:
    """The keepaway trainer of a deep learner: the simulated oracle (against the hand-coded keepers or a
    checkpoint) or a replayed log."""
    if cfg.trainer.name == "replay":
        check_replay_log(cfg)
        return
    if OmegaConf.select(cfg, "trainer.reference") not in (None, "hand"):
        raise ConfigError(
            f"trainer.reference={cfg.trainer.reference!r} with agent=dqn: the oracle judges against the "
            "hand-coded keepers; allowed: null, hand"
        )
    require_float(cfg, "trainer.frequency", 0.0, 1.0)
    require_float(cfg, "trainer.consistency", 0.0, 1.0)
    require_float(cfg, "trainer.reaction", 1e-6)
    if require_bool(cfg, "trainer.timing.enabled"):
        check_timing(cfg, tetris=False)


# ------------------------------------------------------------------------------- gym

GYM_TRAINERS = ("none", "oracle", "value_proxy", "replay", "interactive")


def _task_key(cfg: DictConfig) -> str:
    make = OmegaConf.select(cfg, "domain.make")
    return f"domain.make={make!r}" if make is not None else f"domain.env_id={cfg.domain.env_id!r}"


def gym_spaces(cfg: DictConfig) -> TaskSpaces:
    """The spaces of ``domain=gym``'s task, built once; ``ConfigError`` for an unknown id, a callable that
    does not import or fails, continuous actions, observations neither a vector nor a frame."""
    task = make_gym_task(cfg)
    where = _task_key(cfg)
    try:
        return task_spaces(task)
    except gym.error.Error as exc:
        raise ConfigError(f"{where} is not a Gymnasium task you can make here: {_first(exc)}") from None
    except ValueError as exc:
        raise ConfigError(f"{where} {_first(exc)}") from None
    except Exception as exc:  # a user's factory may fail in any way
        raise ConfigError(f"{where} failed to make the task: {type(exc).__name__}: {_first(exc)}") from None


def _first(exc: BaseException) -> str:
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


def check_gym_domain(cfg: DictConfig) -> None:
    """``domain=gym``: the task (a registered id or a callable) and that it has discrete actions and vector
    or frame observations, its time limit and the simulated trainer's clock."""
    make = OmegaConf.select(cfg, "domain.make")
    env_id = OmegaConf.select(cfg, "domain.env_id")
    if make is None and (not isinstance(env_id, str) or not env_id):
        raise ConfigError(f"domain.env_id={env_id!r} is invalid: name a Gymnasium id, or set domain.make")
    if OmegaConf.select(cfg, "domain.max_episode_steps") is not None:
        require_int(cfg, "domain.max_episode_steps", 1)
    require_float(cfg, "domain.seconds_per_step", 1e-6)
    require_float(cfg, "domain.min_return")
    require_int(cfg, "domain.batch", 1, 4096)
    gym_spaces(cfg)


def plays_on_domain_task(policy: object) -> bool:
    """Whether ``evaluate.py domain=gym policy=...`` plays on ``domain``'s task: ``random`` (or none) and a
    reference ``module:callable``; a run directory or checkpoint brings its own task."""
    return policy in (None, "random") or (":" in str(policy) and not Path(str(policy)).exists())


def check_gym_evaluation(cfg: DictConfig) -> None:
    """``evaluate.py`` on ``domain=gym``: the episodes, the batch and the task (of ``policy=random`` or a
    reference callable; a checkpoint brings its own)."""
    require_int(cfg, "episodes", 1)
    require_int(cfg, "domain.batch", 1, 4096)
    if plays_on_domain_task(OmegaConf.select(cfg, "policy")):
        check_gym_domain(cfg)


def check_gym_dqn(cfg: DictConfig) -> None:
    """DQN on any task: H^ (Deep TAMER on the observation), and the oracle against ``trainer.reference``, a
    replayed log or a person in the browser."""
    check_dqn(cfg, page=True)
    if cfg.trainer.name != "none":
        check_gym_trainer(cfg)


def check_gym_tamer(cfg: DictConfig) -> None:
    """TAMER alone on any task: its budget, Deep TAMER's H^ on the observation, and the trainer it cannot do
    without (the oracle against ``trainer.reference``, the value proxy, a replayed log or a person), which
    may leave (``trainer.leave_after``)."""
    a = "agent."
    frames = require_int(cfg, a + "frames", 1)
    require_int(cfg, a + "boards", 1, 4096)
    require_int(cfg, a + "eval_every", 1, max(frames, 1))
    require_int(cfg, a + "eval_episodes", 1, 4096)
    fusion, trainer = cfg.fusion.name, cfg.trainer.name
    if fusion != "none":
        picked = " (trainer=interactive picks fusion=linear unless told)" if trainer == "interactive" else ""
        raise ConfigError(
            f"fusion={fusion!r} with agent=tamer{picked}: TAMER acts on H^ alone; use fusion=none, or "
            f"agent=dqn fusion={fusion} to fuse H^ with a DQN"
        )
    if trainer == "none":
        raise ConfigError(
            "trainer=none with agent=tamer: TAMER alone learns only from a trainer's feedback; "
            "choose trainer=oracle (with trainer.reference=...), value_proxy, replay or interactive"
        )
    check_gym_trainer(cfg)
    check_departure(cfg)


def check_gym_ppo(cfg: DictConfig) -> None:
    """PPO on any task: its budget, networks and loss, the fusion schemes that act on a softmax policy, H^
    and its trainer (the oracle against ``trainer.reference``, the value proxy, a replayed log, a person)."""
    a = "agent."
    require_int(cfg, a + "frames", 1)
    boards = require_int(cfg, a + "boards", 1, 4096)
    steps = require_int(cfg, a + "steps_per_batch", 1, 10_000)
    require_int(cfg, a + "eval_every", 1)
    require_int(cfg, a + "eval_episodes", 1, 10_000)
    require_int(cfg, a + "minibatch_size", 1, boards * steps)
    require_int(cfg, a + "epochs", 1, 1000)
    require_float(cfg, a + "lr", 1e-12)
    require_float(cfg, a + "gamma", 0.0, 1.0)
    require_float(cfg, a + "lmbda", 0.0, 1.0)
    require_float(cfg, a + "clip_epsilon", 1e-6, 1.0)
    require_float(cfg, a + "entropy_coeff", 0.0)
    require_float(cfg, a + "critic_coeff", 0.0)
    require_float(cfg, a + "max_grad_norm", 1e-12)
    check_cells(cfg, a + "cells")
    fusion = cfg.fusion.name
    if fusion in PPO_REFUSED:
        raise ConfigError(
            f"fusion={fusion!r} with agent=ppo is invalid: {PPO_REFUSED[fusion]}; allowed: "
            f"{', '.join(f for f in FUSIONS if f not in PPO_REFUSED)}"
        )
    if fusion != "none" and OmegaConf.select(cfg, "fusion.normalise") is True:
        raise ConfigError(
            "fusion.normalise=true with agent=ppo is invalid: rescaling the logits to [0, 1] per decision "
            "caps how sure the softmax policy can be; allowed: null, false, spread"
        )
    trainer = cfg.trainer.name
    if trainer == "none":
        if fusion != "none":
            raise ConfigError(
                f"fusion={fusion!r} fuses a trainer's H^ into the learner; choose a trainer: oracle "
                "(or fusion=none)"
            )
        return
    check_gym_trainer(cfg)


def check_gym_trainer(cfg: DictConfig) -> None:
    """The trainer of a taught ``domain=gym`` learner (every learner takes each of ``GYM_TRAINERS``): the
    oracle against ``trainer.reference``, its noise and timing, and Deep TAMER's H^ (``human=mlp``) that
    learns from it."""
    trainer = cfg.trainer.name
    taught = [t for t in GYM_TRAINERS if t != "none"]
    if trainer not in taught:
        raise ConfigError(f"trainer={trainer} is not available for domain=gym; allowed: {', '.join(taught)}")
    require_choice(cfg, "human.name", ("mlp",))
    check_mlp_human(cfg, placements=False)
    if trainer == "interactive":
        check_interactive(cfg)
        check_gym_frames(cfg)
        return
    if trainer == "replay":
        check_replay_log(cfg)
    elif trainer == "value_proxy":
        require_choice(cfg, "trainer.mode", ("sign", "scaled"))
        require_float(cfg, "trainer.scale", 1e-12)
        check_gym_reference(cfg, values=True)
    else:
        check_gym_reference(cfg)
        require_float(cfg, "trainer.frequency", 0.0, 1.0)
        require_float(cfg, "trainer.consistency", 0.0, 1.0)
    require_float(cfg, "trainer.reaction", 1e-6)
    if require_bool(cfg, "trainer.timing.enabled"):
        check_timing(cfg, tetris=False)


def check_gym_frames(cfg: DictConfig) -> None:
    """``trainer=interactive`` on ``domain=gym``: the task renders RGB frames for the page (a registered id
    made with ``render_mode="rgb_array"``, or a callable's env made so), tried once."""
    where = f"{_task_key(cfg)} cannot be shown in the browser"
    env = None
    try:
        env = make_gym_task(cfg).make_watched()
        first_frame(env)
    except ValueError as exc:
        raise ConfigError(f"{where}: it {_first(exc)}") from None
    except Exception as exc:  # making or rendering may fail in any way (gymnasium's: a missing pygame)
        raise ConfigError(f"{where}: rendering a frame failed: {type(exc).__name__}: {_first(exc)}") from None
    finally:
        if env is not None:
            env.close()


def check_gym_reference(cfg: DictConfig, values: bool = False) -> None:
    """``trainer.reference``: a callable that imports, or a ``domain=gym`` run directory or checkpoint of
    the task's observation size and action count, that on two of the task's observations returns actions
    [2] or action values [2, A] (``values``: the value proxy's, action values only)."""
    reference = OmegaConf.select(cfg, "trainer.reference")
    if reference is None:
        returning = (
            "returning action values [B, A] of observations [B, ...]"
            if values
            else "a policy of observations [B, S] returning actions [B] or action values [B, A] "
            "(e.g. examples.cartpole:reference)"
        )
        raise ConfigError(
            f"trainer={cfg.trainer.name} on domain=gym needs trainer.reference=<package.module:callable>, "
            f"{returning}, or a domain=gym run directory or checkpoint"
        )
    try:
        policy = make_gym_reference(cfg)
    except CheckpointError as exc:
        raise ConfigError(
            f"trainer.reference={reference!r} is not a checkpoint of a domain=gym run ({_first(exc)}); "
            "allowed: a domain=gym run directory or checkpoint, or package.module:callable"
        ) from None
    spaces = gym_spaces(cfg)
    if isinstance(policy, PolicyReference):
        saved = (policy.observation_size, policy.actions)
        if saved != (spaces.observation_size, spaces.actions):
            raise ConfigError(
                f"trainer.reference={reference!r} plays observations of size {saved[0]} with {saved[1]} "
                f"actions; {_task_key(cfg)} has observations of size {spaces.observation_size} and "
                f"{spaces.actions} actions"
            )
    try:
        if values:
            action_values(values_of(policy), spaces.sample.clone(), spaces.actions)
        else:
            right_actions(policy, spaces.sample.clone(), spaces.actions)
    except ValueError as exc:
        raise ConfigError(f"trainer.reference={reference!r} {_first(exc)}") from None
    except Exception as exc:  # the user's policy may fail in any way
        raise ConfigError(
            f"trainer.reference={reference!r} failed on observations of shape {list(spaces.sample.shape)}: "
            f"{type(exc).__name__}: {_first(exc)}"
        ) from None
