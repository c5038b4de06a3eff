"""Q-learning on Tetris: ``run_qlearning`` plays and learns; ``train_qlearning`` is ``agent=qlearning``.

One batched ``TetrisEnv`` holds every learner's board (B = learners), so ten seeds are one run. Each loop
iteration is one placement on every board: choose epsilon-greedily, step the env (finished games restart),
make the TD update with the reward and the next state's placements, and book the lines of every game that
ended. A learner that has played its ``games`` games stops: its board keeps playing (the env resets it like
any other) but it learns nothing more and is not counted.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch import keys
from hfrl_torch.agents.qlearning import LinearQLearning
from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.logger import flatten_config, markdown_table
from hfrl_torch.common.validation import require_choice, require_float, require_int
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.features import feature_id, feature_names
from hfrl_torch.experiment.game_curves import greedy_evaluation, write_game_curves

FEATURES = ("bt", "knox", "dellacherie", "dt")


def epsilon_schedule(
    epsilon: float, decay: float, minimum: float, games_played: torch.Tensor
) -> torch.Tensor:
    """Exploration rate ``[L]`` of each learner's current game: max(epsilon * decay^games_played, minimum)."""
    return (epsilon * decay ** games_played.to(torch.float64)).clamp(min=minimum)


def run_qlearning(
    rules: TetrisRules,
    games: int,
    alpha: float,
    gamma: float,
    epsilon: float,
    learners: int = 1,
    seed: int = 0,
    *,
    epsilon_decay: float = 1.0,
    epsilon_min: float = 0.0,
    features: str = "bt",
    max_pieces: int = 0,
    agent: LinearQLearning | None = None,
    on_games_done: Callable[[int], None] | None = None,
) -> dict[str, object]:
    """Train ``learners`` independent Q-learners for ``games`` games each on boards of ``rules``.

    :param rules: board size and rule options.
    :param games: games per learner.
    :param alpha: the step size; ``gamma``: the discount factor.
    :param epsilon: exploration rate of the first game, multiplied by ``epsilon_decay`` after each of the
        learner's games and kept at least ``epsilon_min``.
    :param learners: independent learners, one board each.
    :param seed: seeds the env's games and (with ``2 * seed + 1``) the exploration draws.
    :param features: the afterstate feature set (``bt``: the thesis's 21).
    :param max_pieces: cap every game at this many placements (0 = play to the end; a capped game still
        bootstraps from its last state, since it did not end).
    :param agent: a LinearQLearning to continue training (default a new one with weights 0).
    :param on_games_done: called with the number of games that just ended (for a progress bar).
    :return: ``lines`` and ``pieces`` [learners, games] int64, ``td_error`` [learners, games] (mean |delta|
        over each game's placements), ``weights`` [learners, F], ``bias`` [learners] and ``agent``.
    """
    if games < 1 or learners < 1:
        raise ValueError(f"run_qlearning needs games >= 1 and learners >= 1, got {games} and {learners}")
    env = TetrisEnv(batch=learners, rules=rules, features=features, max_pieces=max_pieces, seed=seed)
    if agent is None:
        agent = LinearQLearning(env.num_features, learners, alpha, gamma, seed=2 * seed + 1)
    lines = torch.zeros(learners, games, dtype=torch.int64)
    pieces = torch.zeros(learners, games, dtype=torch.int64)
    td_error = torch.zeros(learners, games, dtype=torch.float64)
    abs_delta = torch.zeros(learners, dtype=torch.float64)  # summed over the current game
    played = torch.zeros(learners, dtype=torch.int64)

    td = env.reset()
    while bool((played < games).any()):
        active = played < games
        feats = td[keys.AFTERSTATE_FEATURES]
        eps = epsilon_schedule(epsilon, epsilon_decay, epsilon_min, played)
        action = agent.act(feats, td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL], eps)

        td[keys.ACTION] = action
        td, td_next = env.step_and_maybe_reset(td)
        nxt = td["next"]
        chosen = feats[torch.arange(learners), action]
        delta = agent.td_update(
            chosen,
            nxt[keys.REWARD].view(-1),
            nxt[keys.AFTERSTATE_FEATURES],
            nxt[keys.ACTION_MASK],
            nxt[keys.AFTERSTATE_TERMINAL],
            nxt[keys.TERMINATED].view(-1),
            active,
        )
        abs_delta += delta.abs()

        done = nxt[keys.DONE].view(-1) & active
        if bool(done.any()):
            rows = done.nonzero().flatten()
            idx = played[rows]
            lines[rows, idx] = nxt[keys.LINES].view(-1)[rows]
            pieces[rows, idx] = nxt[keys.PIECES_PLACED].view(-1)[rows]
            td_error[rows, idx] = abs_delta[rows] / pieces[rows, idx].clamp(min=1)
            abs_delta[rows] = 0.0
            played += done.to(torch.int64)
            if on_games_done is not None:
                on_games_done(int(done.sum()))
        td = td_next

    return {
        "lines": lines,
        "pieces": pieces,
        "td_error": td_error,
        "weights": agent.weight.detach().clone(),
        "bias": agent.bias.detach().clone(),
        "agent": agent,
    }


def check_qlearning(cfg: DictConfig) -> None:
    """Check ``agent`` for Q-learning: one line naming a bad value and what is allowed."""
    require_choice(cfg, "agent.name", ("qlearning",))
    require_int(cfg, "agent.games", 1)
    require_int(cfg, "agent.learners", 1, 100_000)
    require_float(cfg, "agent.alpha", 1e-12)
    require_float(cfg, "agent.gamma", 0.0, 1.0)
    require_float(cfg, "agent.epsilon", 0.0, 1.0)
    require_float(cfg, "agent.epsilon_decay", 0.0, 1.0)
    require_float(cfg, "agent.epsilon_min", 0.0, 1.0)
    require_choice(cfg, "agent.features", FEATURES)
    require_int(cfg, "agent.eval_games", 0)
    environment_only(cfg)


def environment_only(cfg: DictConfig) -> None:
    """Refuse a trainer or a fusion scheme: this agent learns from the environment's reward alone."""
    for group in ("trainer", "fusion"):
        name = OmegaConf.select(cfg, f"{group}.name")
        if name != "none":
            raise ConfigError(
                f"{group}={name!r} with agent={cfg.agent.name}: this learner uses the environment's reward "
                f"alone (no human feedback yet); use {group}=none"
            )


def train_qlearning(cfg: DictConfig, run_dir: Path) -> dict[str, float]:
    """``train.py agent=qlearning``: run the Q-learners, log one point per game, checkpoint learner 0.

    TensorBoard and ``metrics.jsonl`` get, per game number, the lines per game over the learners (mean,
    median, 95 % interval), the mean |TD error| and the exploration rate; at the end each learner's greedy
    policy plays ``agent.eval_games`` fresh games.
    """
    from hfrl_torch.experiment.factories import make_rules, make_run_logger

    check_qlearning(cfg)
    rules = make_rules(cfg)
    a = cfg.agent
    logger = make_run_logger(cfg, str(run_dir / "tensorboard"), purge_step=None)
    logger.text("hyperparameters", markdown_table(flatten_config(cfg)))
    logger.text("rules", f"{rules.describe()}, board {rules.width}x{rules.height}, features {a.features}")

    bar = tqdm(total=a.learners * a.games, desc=f"Q-learning {rules.width}x{rules.height}", unit="game")
    try:
        out = run_qlearning(
            rules,
            a.games,
            a.alpha,
            a.gamma,
            a.epsilon,
            learners=a.learners,
            seed=cfg.seed,
            epsilon_decay=a.epsilon_decay,
            epsilon_min=a.epsilon_min,
            features=a.features,
            max_pieces=cfg.domain.max_pieces,
            on_games_done=bar.update,
        )
    finally:
        bar.close()

    eps = epsilon_schedule(a.epsilon, a.epsilon_decay, a.epsilon_min, torch.arange(a.games))
    history = write_game_curves(
        out["lines"],
        logger,
        run_dir,
        lambda g: {
            "train/td_error_mean": float(out["td_error"][:, g].mean()),
            "train/epsilon": float(eps[g]),
            "train/pieces_per_game": float(out["pieces"][:, g].double().mean()),
        },
    )

    weights = out["weights"]
    final = dict(history[-1])
    if a.eval_games > 0:
        final.update(greedy_evaluation(cfg, weights, a.eval_games))
        logger.scalars({k: v for k, v in final.items() if k.startswith("eval/greedy")}, a.games)
    save_checkpoint(
        run_dir / "checkpoints" / LAST,
        domain="tetris",
        agent="qlearning",
        config_yaml=OmegaConf.to_yaml(cfg, resolve=True),
        payload={
            "state": {"weights": weights.clone(), "bias": out["bias"].clone(), "lines": out["lines"].clone()},
            "history": history,
            # Q(s, a) = w . f(s'_a) + b: the bias is the same for every placement, so argmax_a Q is the
            # linear afterstate policy w
            "policy": {
                "kind": "linear",
                "features": a.features,
                "feature_names": feature_names(feature_id(a.features), rules.width),
                "weights": weights[0].clone(),
                "note": "learner 0 of the run",
            },
            "rules": rules.as_dict(),
        },
    )
    logger.hparams(flatten_config(cfg), {"hparam/lines_last_game": final["eval/lines_per_game_mean"]})
    logger.close()
    return final
