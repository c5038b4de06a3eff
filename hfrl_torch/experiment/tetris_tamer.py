"""TAMER on Tetris with a trainer in the loop: ``run_tamer`` plays, gives feedback, learns, and reports.

One batched ``TetrisEnv`` holds every learner's board (B = learners), so ten seeds are one run. Each
loop iteration is one placement on every board at the same clock time: apply the feedback that is due,
choose greedily under H^, let the trainer judge the placement, step the env (finished games restart),
and book the lines of every game that ended. A learner that has played its ``games`` games stops: its
board keeps playing (the env resets it like any other) but gets no feedback, learns nothing and is
not counted.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from hfrl_torch import keys
from hfrl_torch.agents.tamer import TamerAgent
from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.logger import flatten_config, markdown_table
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.features import feature_id, feature_names
from hfrl_torch.experiment.game_curves import write_game_curves
from hfrl_torch.feedback.credit import CreditModel
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.base import Trainer


def run_tamer(
    rules: TetrisRules,
    games: int,
    trainer: Trainer,
    alpha: float,
    learners: int = 1,
    seed: int = 0,
    *,
    features: str = "knox",
    credit: CreditModel | None = None,
    window: float | None = 0.5,
    renormalise: bool = False,
    max_pieces: int = 0,
    seconds_per_placement: float = 1.0,
    clock: Callable[[], float] | None = None,
    agent: TamerAgent | None = None,
    on_games_done: Callable[[int], None] | None = None,
) -> dict[str, object]:
    """Train ``learners`` independent TAMER learners for ``games`` games each with ``trainer``'s feedback.

    :param rules: board size and rule options.
    :param games: games per learner; game g of every learner counts from its first placement.
    :param trainer: gives the feedback (oracle, value proxy, timing wrapper, replay, queue).
    :param alpha: TAMER's step size.
    :param learners: independent learners, one board each.
    :param seed: seeds the env's games (the trainer has its own seed).
    :param features: ``knox`` (46, Knox's TAMER set) or ``bt`` (the thesis's 21).
    :param credit: the agent's credit model (default ``PreviousStep``).
    :param window: longest delay credited, seconds (delay densities only).
    :param renormalise: renormalise each event's credits (delay densities only).
    :param max_pieces: cap every game at this many placements (0 = play to the end).
    :param seconds_per_placement: the simulated clock's time per placement (a placement with its
        falling animation: about five primitive moves at 5 per second).
    :param clock: a real clock (e.g. ``time.time``) for a live trainer instead of the simulated one.
    :param agent: a TamerAgent to continue training (default a new one with weights 0).
    :param on_games_done: called with the number of games that just ended (for a progress bar).
    :return: ``lines`` and ``pieces`` [learners, games] int64, ``feedback``, ``positive``, ``negative``
        (events given per learner) and ``applied`` (events learned from) [learners], ``given_per_game``
        [learners, games, 3] (events given during each game: all, positive, negative), ``weights``
        [learners, F], ``agent`` and ``alpha``.
    """
    if games < 1 or learners < 1:
        raise ValueError(f"run_tamer needs games >= 1 and learners >= 1, got {games} and {learners}")
    env = TetrisEnv(batch=learners, rules=rules, features=features, max_pieces=max_pieces, seed=seed)
    if agent is None:
        agent = TamerAgent(env.num_features, learners, alpha, credit, window, renormalise)
    lines = torch.zeros(learners, games, dtype=torch.int64)
    pieces = torch.zeros(learners, games, dtype=torch.int64)
    played = torch.zeros(learners, dtype=torch.int64)
    given = torch.zeros(learners, games, 3, dtype=torch.int64)  # all, positive, negative
    placement = 0

    td = env.reset()
    while bool((played < games).any()):
        now = clock() if clock is not None else placement * seconds_per_placement
        active = played < games
        agent.learn(now)

        action = agent.act(td)
        events = trainer.give(td, action, now, played, active)
        agent.record(td, action, now, active)
        agent.give_feedback(events, active)
        for i, evs in enumerate(events):
            g = min(int(played[i]), games - 1)
            given[i, g, 0] += len(evs)
            given[i, g, 1] += sum(e.value > 0 for e in evs)
            given[i, g, 2] += sum(e.value < 0 for e in evs)

        td[keys.ACTION] = action
        td, td_next = env.step_and_maybe_reset(td)
        done = td["next", keys.DONE].view(-1) & active
        if bool(done.any()):
            game_lines = td["next", keys.LINES].view(-1)
            idx = played.clamp(max=games - 1)
            rows = done.nonzero().flatten()
            lines[rows, idx[rows]] = game_lines[rows]
            pieces[rows, idx[rows]] = td["next", keys.PIECES_PLACED].view(-1)[rows]
            trainer.end_games(done, game_lines)
            played += done.to(torch.int64)
            if on_games_done is not None:
                on_games_done(int(done.sum()))
        td = td_next
        placement += 1

    return {
        "lines": lines,
        "pieces": pieces,
        "feedback": given[..., 0].sum(1),
        "positive": given[..., 1].sum(1),
        "negative": given[..., 2].sum(1),
        "given_per_game": given,
        "applied": agent.applied.clone(),
        "weights": agent.model.weight.detach().clone(),
        "agent": agent,
        "alpha": alpha,
    }


def train_tamer(cfg: DictConfig, run_dir: Path) -> dict[str, float]:
    """``train.py agent=tamer``: run TAMER learners with the configured trainer, log and checkpoint.

    TensorBoard gets one point per game (x = game number): lines per game over learners with a 95 %
    interval, feedback given and its positive share; the trainer is named in the logs as what it is
    (a simulated trainer or a replayed log). Every event goes to ``feedback.jsonl`` as it is given.
    """
    from hfrl_torch.experiment.factories import make_credit, make_rules, make_run_logger, make_trainer

    rules = make_rules(cfg)
    a, hm = cfg.agent, cfg.human
    log = FeedbackLog(run_dir / "feedback.jsonl", session=run_dir.name)
    trainer = make_trainer(cfg, log)
    source = trainer.source if trainer.source != "trainer" else f"simulated:{cfg.trainer.name}"
    logger = make_run_logger(cfg, str(run_dir / "tensorboard"), purge_step=None)
    logger.text("hyperparameters", markdown_table(flatten_config(cfg)))
    logger.text(
        "trainer", f"{source} (trainer={cfg.trainer.name}; a simulated or replayed trainer, not a person)"
    )

    bar = tqdm(total=a.learners * a.games, desc=f"TAMER {rules.width}x{rules.height}", unit="game")
    try:
        out = run_tamer(
            rules,
            a.games,
            trainer,
            hm.alpha,
            learners=a.learners,
            seed=cfg.seed,
            features=hm.features,
            credit=make_credit(cfg),
            window=hm.window,
            renormalise=hm.renormalise,
            max_pieces=cfg.domain.max_pieces,
            seconds_per_placement=hm.seconds_per_placement,
            on_games_done=bar.update,
        )
    finally:
        bar.close()
        log.close()

    given = out["given_per_game"].double()

    def feedback(g: int) -> dict[str, float]:
        fb = given[:, g, 0]
        return {
            "feedback/given_mean": float(fb.mean()),
            "feedback/positive_share": float(given[:, g, 1].sum() / fb.sum()) if fb.sum() > 0 else 0.0,
        }

    history = write_game_curves(out["lines"], logger, run_dir, feedback)
    weights = out["weights"]
    save_checkpoint(
        run_dir / "checkpoints" / LAST,
        domain="tetris",
        agent="tamer",
        config_yaml=OmegaConf.to_yaml(cfg, resolve=True),
        payload={
            "state": {"weights": weights.clone(), "lines": out["lines"].clone()},
            "history": history,
            # argmax_a w.(f(s'_a) - f(s)) = argmax_a w.f(s'_a): H^ acts as a linear afterstate policy
            "policy": {
                "kind": "linear",
                "features": hm.features,
                "feature_names": feature_names(feature_id(hm.features), rules.width),
                "weights": weights[0].clone(),
                "note": "learner 0 of the run",
            },
            "rules": rules.as_dict(),
        },
    )
    final = history[-1]
    logger.hparams(flatten_config(cfg), {"hparam/lines_last_game": final["eval/lines_per_game_mean"]})
    logger.close()
    return {**final, "feedback_events": float(out["feedback"].sum())}
