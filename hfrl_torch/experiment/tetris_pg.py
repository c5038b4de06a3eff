"""Policy gradient on Tetris: ``run_pg`` plays and learns, ``train_pg`` is ``train.py agent=pg``.

One batched ``TetrisEnv`` holds every learner's board (B = learners), so ten seeds are one run. Each loop
iteration is one placement on every board: sample from each learner's softmax policy, add the score (and
the Fisher matrix) to its game in progress, step the env (finished games restart), and close the games
that ended with their lines as the return; a learner steps its weights every ``games_per_update`` games.
A learner that has played its ``games`` games stops: its board keeps playing (the env resets it like any
other) but it learns nothing more and is not counted.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch import keys
from hfrl_torch.agents.pg import PolicyGradient
from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.logger import flatten_config, markdown_table
from hfrl_torch.common.stats import summarize
from hfrl_torch.common.validation import require_bool, require_choice, require_float, require_int
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.features import feature_id, feature_names
from hfrl_torch.experiment.tetris_qlearning import FEATURES, environment_only, greedy_evaluation


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
    :return: ``lines`` and ``pieces`` [learners, games] int64, ``weights`` [learners, F], ``updates``
        [learners] (gradient steps taken) and ``agent``.
    """
    if games < 1 or learners < 1:
        raise ValueError(f"run_pg needs games >= 1 and learners >= 1, got {games} and {learners}")
    env = TetrisEnv(batch=learners, rules=rules, features=features, max_pieces=max_pieces, seed=seed)
    if agent is None:
        agent = PolicyGradient(
            env.num_features,
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

    td = env.reset()
    while bool((played < games).any()):
        active = played < games
        feats, mask, terminal = (
            td[keys.AFTERSTATE_FEATURES],
            td[keys.ACTION_MASK],
            td[keys.AFTERSTATE_TERMINAL],
        )
        action = agent.act(feats, mask, terminal)
        agent.record(feats, mask, terminal, action, active)

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
            played += done.to(torch.int64)
            if on_games_done is not None:
                on_games_done(int(done.sum()))
        td = td_next

    return {
        "lines": lines,
        "pieces": pieces,
        "weights": agent.weight.detach().clone(),
        "updates": agent.updates.clone(),
        "agent": agent,
    }


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
    environment_only(cfg)


def train_pg(cfg: DictConfig, run_dir: Path) -> dict[str, float]:
    """``train.py agent=pg``: run the policy-gradient learners, log one point per game, checkpoint learner 0.

    TensorBoard and ``metrics.jsonl`` get, per game number, the lines per game of the learners' stochastic
    policies (mean, median, 95 % interval); at the end each learner's greedy policy (argmax of theta . f)
    plays ``agent.eval_games`` fresh games.
    """
    from hfrl_torch.experiment.factories import make_rules, make_run_logger

    check_pg(cfg)
    rules = make_rules(cfg)
    a = cfg.agent
    logger = make_run_logger(cfg, str(run_dir / "tensorboard"), purge_step=None)
    logger.text("hyperparameters", markdown_table(flatten_config(cfg)))
    logger.text("rules", f"{rules.describe()}, board {rules.width}x{rules.height}, features {a.features}")

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
        )
    finally:
        bar.close()

    lines = out["lines"].double()
    history = []
    for g in range(a.games):
        s = summarize(lines[:, g], floor=0.0)
        metrics = {
            "eval/lines_per_game_mean": s["mean"],
            "eval/lines_per_game_median": s["median"],
            "eval/lines_per_game_ci95_low": s["ci95_low"],
            "eval/lines_per_game_ci95_high": s["ci95_high"],
            "train/pieces_per_game": float(out["pieces"][:, g].double().mean()),
        }
        logger.scalars(metrics, g + 1)
        history.append({"game": g + 1, **metrics})
    with (run_dir / "metrics.jsonl").open("w") as f:
        f.writelines(json.dumps(h) + "\n" for h in history)

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
