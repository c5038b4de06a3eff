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

import torch

from hfrl_torch import keys
from hfrl_torch.agents.tamer import TamerAgent
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.feedback.credit import CreditModel
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
    :return: ``lines`` and ``pieces`` [learners, games] int64, ``feedback``, ``positive``, ``negative``
        (events given per learner) and ``applied`` (events learned from) [learners], ``weights``
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
    given = torch.zeros(learners, 3, dtype=torch.int64)  # all, positive, negative
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
            given[i, 0] += len(evs)
            given[i, 1] += sum(e.value > 0 for e in evs)
            given[i, 2] += sum(e.value < 0 for e in evs)

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
        td = td_next
        placement += 1

    return {
        "lines": lines,
        "pieces": pieces,
        "feedback": given[:, 0],
        "positive": given[:, 1],
        "negative": given[:, 2],
        "applied": agent.applied.clone(),
        "weights": agent.model.weight.detach().clone(),
        "agent": agent,
        "alpha": alpha,
    }
