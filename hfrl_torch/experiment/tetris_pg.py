"""Policy gradient on Tetris: ``run_pg`` plays and learns, ``train_pg`` is ``train.py agent=pg``.

One batched ``TetrisEnv`` holds every learner's board (B = learners), so ten seeds are one run. Each loop
iteration is one placement on every board: sample from each learner's softmax policy, add the score (and
the Fisher matrix) to its game in progress, step the env (finished games restart), and close the games
that ended with their lines as the return; a learner steps its weights every ``games_per_update`` games.
A learner that has played its ``games`` games stops: its board keeps playing (the env resets it like any
other) but it learns nothing more and is not counted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch import keys
from hfrl_torch.agents.pg import PolicyGradient
from hfrl_torch.agents.tamer import TamerAgent
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.logger import flatten_config, markdown_table
from hfrl_torch.common.validation import require_bool, require_choice, require_float, require_int
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.features import feature_id, feature_names, feature_size
from hfrl_torch.experiment.game_curves import greedy_evaluation, write_game_curves
from hfrl_torch.experiment.tetris_qlearning import FEATURES
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.schedules import WeightSchedule
from hfrl_torch.models.linear import greedy_placement
from hfrl_torch.trainers.base import Trainer

PG_FUSIONS = ("none", "linear", "annealed")


def run_pg(
    rules: TetrisRules,
    games: int,
    lr: float,
    learners: int = 1,
    seed: int = 0,
    *,
    natural: bool = False,
    damping: float = 1.0,
    temperature: float = 1.0,
    games_per_update: int = 1,
    baseline_decay: float = 0.9,
    features: str = "bt",
    max_pieces: int = 0,
    agent: PolicyGradient | None = None,
    on_games_done: Callable[[int], None] | None = None,
    trainer: Trainer | None = None,
    human: TamerAgent | None = None,
    weights: WeightSchedule | None = None,
    human_features: str = "knox",
    seconds_per_placement: float = 1.0,
) -> dict[str, object]:
    """Train ``learners`` independent policy-gradient learners for ``games`` games each.

    :param rules: board size and rule options.
    :param games: games per learner.
    :param lr: the step size; ``natural``, ``damping``, ``temperature``, ``games_per_update`` and
        ``baseline_decay`` as in :class:`PolicyGradient`.
    :param learners: independent learners, one board each.
    :param seed: seeds the env's games and (with ``2 * seed + 1``) the sampling of placements.
    :param features: the afterstate feature set (``bt``: the thesis's 21).
    :param max_pieces: cap every game at this many placements (0 = play to the end); a capped game's
        return is the lines it cleared until then.
    :param agent: a PolicyGradient to continue training (default a new one with weights 0).
    :param on_games_done: called with the number of games that just ended (for a progress bar).
    :param trainer: with ``human`` and ``weights``: PG + human feedback (thesis Figure 4.2). The trainer
        judges every placement of every board (one simulated trainer per learner), H^ (``human``, one per
        learner, over ``human_features`` changes) learns from it, and each learner samples from
        pi ~ exp((theta . f + w H^) / T), w its weight (trust factor: eq. 4.4 after each of its games, from
        the game's lines and the share of its placements where argmax H^ = argmax theta . f).
    :param seconds_per_placement: the simulated clock of the trainer's events.
    :return: ``lines`` and ``pieces`` [learners, games] int64, ``weights`` [learners, F], ``updates``
        [learners] (gradient steps taken) and ``agent``; with a trainer also ``given`` [learners, games]
        (events per game), ``weight`` and ``match_rate`` [learners, games] (the weight used in each game
        and its match rate).
    """
    if games < 1 or learners < 1:
        raise ValueError(f"run_pg needs games >= 1 and learners >= 1, got {games} and {learners}")
    if trainer is not None and (human is None or weights is None):
        raise ValueError("run_pg with a trainer needs human (a TamerAgent) and weights (a WeightSchedule)")
    env_features = human_features if trainer is not None else features
    env = TetrisEnv(batch=learners, rules=rules, features=env_features, max_pieces=max_pieces, seed=seed)
    n_pg = feature_size(feature_id(features), rules.width)
    if agent is None:
        agent = PolicyGradient(
            n_pg,
            learners,
            lr,
            temperature,
            natural,
            damping,
            games_per_update,
            baseline_decay,
            seed=2 * seed + 1,
        )
    lines = torch.zeros(learners, games, dtype=torch.int64)
    pieces = torch.zeros(learners, games, dtype=torch.int64)
    played = torch.zeros(learners, dtype=torch.int64)
    given = torch.zeros(learners, games, dtype=torch.int64)
    used_weight = torch.zeros(learners, games, dtype=torch.float64)
    match_rate = torch.full((learners, games), math.nan, dtype=torch.float64)
    matches = torch.zeros(learners, dtype=torch.int64)
    decisions = torch.zeros(learners, dtype=torch.int64)
    placement = 0

    td = env.reset()
    while bool((played < games).any()):
        active = played < games
        now = placement * seconds_per_placement
        feats, mask, terminal = (
            td[keys.AFTERSTATE_FEATURES][..., :n_pg],
            td[keys.ACTION_MASK],
            td[keys.AFTERSTATE_TERMINAL],
        )
        bias = None
        if trainer is not None:
            human.learn(now)
            h_values = human.model(placement_deltas(td))
            w = weights.value().reshape(-1).expand(learners)
            bias = w.unsqueeze(-1) * h_values
            env_values = torch.einsum("laf,lf->la", feats.to(torch.float64), agent.weight)
            same = greedy_placement(h_values, mask, terminal) == greedy_placement(env_values, mask, terminal)
            matches += (same & active).to(torch.int64)
            decisions += active.to(torch.int64)
            idx = played.clamp(max=games - 1)
            used_weight[torch.arange(learners), idx] = torch.where(
                active, w, used_weight[torch.arange(learners), idx]
            )
        action = agent.act(feats, mask, terminal, bias)
        agent.record(feats, mask, terminal, action, active, bias)
        if trainer is not None:
            events = trainer.give(td, action, now, played, active)
            human.record(td, action, now, active)
            human.give_feedback(events, active)
            count = torch.tensor([len(e) for e in events], dtype=torch.int64)
            idx = played.clamp(max=games - 1)
            given[torch.arange(learners), idx] += torch.where(active, count, 0)

        td[keys.ACTION] = action
        td, td_next = env.step_and_maybe_reset(td)
        nxt = td["next"]
        done = nxt[keys.DONE].view(-1) & active
        if bool(done.any()):
            game_lines = nxt[keys.LINES].view(-1)
            agent.end_games(done, game_lines.to(torch.float64))
            rows = done.nonzero().flatten()
            lines[rows, played[rows]] = game_lines[rows]
            pieces[rows, played[rows]] = nxt[keys.PIECES_PLACED].view(-1)[rows]
            if trainer is not None:
                m = torch.where(decisions > 0, matches.double() / decisions.clamp(min=1), math.nan)
                match_rate[rows, played[rows]] = m[rows]
                weights.end_episode(performance=game_lines.to(torch.float64), match_rate=m, ended=done)
                trainer.end_games(done, game_lines)
                matches = torch.where(done, 0, matches)
                decisions = torch.where(done, 0, decisions)
            played += done.to(torch.int64)
            if on_games_done is not None:
                on_games_done(int(done.sum()))
        td = td_next
        placement += 1

    out: dict[str, object] = {
        "lines": lines,
        "pieces": pieces,
        "weights": agent.weight.detach().clone(),
        "updates": agent.updates.clone(),
        "agent": agent,
    }
    if trainer is not None:
        out.update({"given": given, "weight": used_weight, "match_rate": match_rate})
    return out


def check_pg(cfg: DictConfig) -> None:
    """Check ``agent`` for policy gradient: one line naming a bad value and what is allowed."""
    require_choice(cfg, "agent.name", ("pg",))
    require_int(cfg, "agent.games", 1)
    require_int(cfg, "agent.learners", 1, 100_000)
    require_float(cfg, "agent.lr", 1e-12)
    natural = require_bool(cfg, "agent.natural")
    require_float(cfg, "agent.damping", 1e-12 if natural else 0.0)
    require_float(cfg, "agent.temperature", 1e-6)
    require_int(cfg, "agent.games_per_update", 1)
    require_float(cfg, "agent.baseline_decay", 0.0, 1.0)
    require_choice(cfg, "agent.features", FEATURES)
    require_int(cfg, "agent.eval_games", 0)
    fusion, trainer = cfg.fusion.name, cfg.trainer.name
    if trainer == "none":
        if fusion != "none":
            raise ConfigError(
                f"fusion={fusion!r} fuses a trainer's H^ into the policy; choose a trainer: oracle, ..."
            )
        return
    from hfrl_torch.experiment.factories import check_human, make_weight_schedule

    if fusion not in PG_FUSIONS:
        raise ConfigError(
            f"fusion={fusion!r} with agent=pg is invalid; allowed: {', '.join(PG_FUSIONS)} (H^ biases the "
            "softmax policy: pi ~ exp((theta . f + w H^) / T))"
        )
    if trainer == "interactive":
        raise ConfigError(
            "trainer=interactive teaches agent=cem; agent=pg takes a simulated trainer or replay"
        )
    if require_choice(cfg, "agent.features", FEATURES) != "bt" or cfg.human.features != "knox":
        raise ConfigError(
            "agent=pg with a trainer needs agent.features=bt and human.features=knox (bt is its prefix)"
        )
    check_human(cfg)
    make_weight_schedule(cfg)


def train_pg(cfg: DictConfig, run_dir: Path) -> dict[str, float]:
    """``train.py agent=pg``: run the policy-gradient learners, log one point per game, checkpoint learner 0.

    TensorBoard and ``metrics.jsonl`` get, per game number, the lines per game of the learners' stochastic
    policies (mean, median, 95 % interval); at the end each learner's greedy policy (argmax of theta . f)
    plays ``agent.eval_games`` fresh games.
    """
    from hfrl_torch.experiment.factories import (
        make_credit,
        make_rules,
        make_run_logger,
        make_trainer,
        make_weight_schedule,
    )

    check_pg(cfg)
    rules = make_rules(cfg)
    a = cfg.agent
    logger = make_run_logger(cfg, str(run_dir / "tensorboard"), purge_step=None)
    logger.text("hyperparameters", markdown_table(flatten_config(cfg)))
    logger.text("rules", f"{rules.describe()}, board {rules.width}x{rules.height}, features {a.features}")
    feedback: dict[str, object] = {}
    log = None
    if cfg.trainer.name != "none":
        hm = cfg.human
        log = FeedbackLog(run_dir / "feedback.jsonl", session=run_dir.name)
        trainer = make_trainer(cfg, log)
        n_h = feature_size(feature_id(hm.features), rules.width)
        feedback = {
            "trainer": trainer,
            "human": TamerAgent(n_h, a.learners, hm.alpha, make_credit(cfg), hm.window, hm.renormalise),
            "weights": make_weight_schedule(cfg, a.learners),
            "human_features": hm.features,
            "seconds_per_placement": hm.seconds_per_placement,
        }
        logger.text(
            "trainer",
            f"{trainer.source} (trainer={cfg.trainer.name}; a simulated or replayed trainer, not a person), "
            f"fusion={cfg.fusion.name}; one trainer per learner",
        )

    kind = "natural PG" if a.natural else "PG"
    bar = tqdm(total=a.learners * a.games, desc=f"{kind} {rules.width}x{rules.height}", unit="game")
    try:
        out = run_pg(
            rules,
            a.games,
            a.lr,
            learners=a.learners,
            seed=cfg.seed,
            natural=a.natural,
            damping=a.damping,
            temperature=a.temperature,
            games_per_update=a.games_per_update,
            baseline_decay=a.baseline_decay,
            features=a.features,
            max_pieces=cfg.domain.max_pieces,
            on_games_done=bar.update,
            **feedback,  # type: ignore[arg-type]
        )
    finally:
        bar.close()
        if log is not None:
            log.close()

    def extra(g: int) -> dict[str, float]:
        metrics = {"train/pieces_per_game": float(out["pieces"][:, g].double().mean())}
        if "given" in out:
            m = out["match_rate"][:, g]
            metrics.update(
                {
                    "feedback/given_mean": float(out["given"][:, g].double().mean()),
                    "fusion/weight_mean": float(out["weight"][:, g].mean()),
                    "fusion/match_rate_mean": float(m[~m.isnan()].mean())
                    if bool((~m.isnan()).any())
                    else math.nan,
                }
            )
        return metrics

    history = write_game_curves(out["lines"], logger, run_dir, extra)

    weights = out["weights"]
    final = dict(history[-1])
    if a.eval_games > 0:
        final.update(greedy_evaluation(cfg, weights, a.eval_games))
        logger.scalars({k: v for k, v in final.items() if k.startswith("eval/greedy")}, a.games)
    save_checkpoint(
        run_dir / "checkpoints" / LAST,
        domain="tetris",
        agent="pg",
        config_yaml=OmegaConf.to_yaml(cfg, resolve=True),
        payload={
            "state": {"weights": weights.clone(), "lines": out["lines"].clone(), "updates": out["updates"]},
            "history": history,
            # evaluate.py plays theta greedily: the most probable placement of the softmax policy
            "policy": {
                "kind": "linear",
                "features": a.features,
                "feature_names": feature_names(feature_id(a.features), rules.width),
                "weights": weights[0].clone(),
                "note": "learner 0 of the run, played greedily",
            },
            "rules": rules.as_dict(),
        },
    )
    logger.hparams(flatten_config(cfg), {"hparam/lines_last_game": final["eval/lines_per_game_mean"]})
    logger.close()
    return final
