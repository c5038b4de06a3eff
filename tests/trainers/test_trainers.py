"""Simulated trainers, replay and the queue trainer: what they give, when, how often, and that it is logged"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
import torch
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.engine_numba import NumbaEngine
from hfrl_torch.envs.tetris.features import DELLACHERIE, DELLACHERIE_WEIGHTS
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, placement_table
from hfrl_torch.feedback.credit import GammaDelay
from hfrl_torch.feedback.events import FeedbackEvent, FeedbackQueue
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.models.linear import greedy_placement
from hfrl_torch.trainers import (
    HumanLikeTiming,
    OracleTrainer,
    QueueTrainer,
    ReplayTrainer,
    ValueProxyTrainer,
    sample_gamma,
)


def _states(batch: int = 8, steps: int = 12, seed: int = 0) -> list[tuple[TensorDict, NumbaEngine]]:
    """Observations of boards played by a mix of good and first-index placements, with engine copies."""
    env = TetrisEnv(batch=batch, rules=TetrisRules(10, 12), features="dellacherie", seed=seed)
    td = env.reset()
    g = torch.Generator().manual_seed(seed)
    w = torch.tensor(DELLACHERIE_WEIGHTS, dtype=torch.float64)
    out = []
    for _ in range(steps):
        eng = NumbaEngine(env.rules, batch, DELLACHERIE)
        for name in ("rows", "heights", "pieces", "keys", "index", "alive"):
            getattr(eng, name)[:] = getattr(env.engine, name)
        out.append((td.clone(), eng))
        good = greedy_placement(td[keys.AFTERSTATE_FEATURES].double() @ w, td[keys.ACTION_MASK])
        td[keys.ACTION] = torch.where(torch.rand(batch, generator=g) < 0.5, good, torch.zeros_like(good))
        _, td = env.step_and_maybe_reset(td)
    return out


def _random_valid(td: TensorDict, g: torch.Generator) -> torch.Tensor:
    return torch.multinomial(td[keys.ACTION_MASK].double(), 1, generator=g).squeeze(-1)


def _board_after(eng: NumbaEngine, b: int, action: int) -> np.ndarray:
    one = NumbaEngine(eng.rules, 1, DELLACHERIE)
    for name in ("rows", "heights", "pieces", "keys", "index", "alive"):
        getattr(one, name)[0] = getattr(eng, name)[b]
    one.step(torch.tensor([action]))
    return one.rows[0].copy()


def _values(events) -> list[float | None]:
    return [evs[0].value if evs else None for evs in events]


def test_oracle_consistent_gives_plus_one_exactly_on_the_reference_board():
    oracle = OracleTrainer(frequency=1.0, consistency=1.0, seed=0)
    g = torch.Generator().manual_seed(1)
    w = torch.tensor(DELLACHERIE_WEIGHTS, dtype=torch.float64)
    n_plus = n_minus = 0
    for td, eng in _states():
        best = greedy_placement(
            td[keys.AFTERSTATE_FEATURES].double() @ w, td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL]
        )
        assert _values(oracle.give(td, best, 0.0, torch.zeros(8))) == [1.0] * 8
        action = _random_valid(td, g)
        for b, v in enumerate(_values(oracle.give(td, action, 0.0, torch.zeros(8)))):
            same = np.array_equal(_board_after(eng, b, int(action[b])), _board_after(eng, b, int(best[b])))
            assert v == (1.0 if same else -1.0)
            n_plus, n_minus = n_plus + (v > 0), n_minus + (v < 0)
    assert n_minus > 0


def test_oracle_inconsistent_flips_every_judgement():
    right, wrong = OracleTrainer(1.0, 1.0, seed=0), OracleTrainer(1.0, 0.0, seed=0)
    g = torch.Generator().manual_seed(2)
    for td, _ in _states(steps=6):
        a = _random_valid(td, g)
        v1 = _values(right.give(td, a, 0.0, torch.zeros(8)))
        v0 = _values(wrong.give(td, a, 0.0, torch.zeros(8)))
        assert v0 == [-v for v in v1]


@pytest.mark.parametrize("frequency", [0.1, 0.5, 0.9])
def test_oracle_frequency_is_the_rate_of_feedback(frequency):
    # 200 steps x 20 boards = 4000 Bernoulli(L) draws: s.d. of the rate <= 0.0079; 4 s.d. = 0.032
    env = TetrisEnv(batch=20, rules=TetrisRules(10, 12), seed=3)
    td = env.reset()
    oracle = OracleTrainer(frequency=frequency, consistency=0.7, seed=11)
    n = sum(
        len(e)
        for _ in range(200)
        for e in oracle.give(td, torch.zeros(20, dtype=torch.int64), 0.0, torch.zeros(20))
    )
    assert abs(n / 4000 - frequency) < 0.032


def test_oracle_consistency_is_the_rate_of_unflipped_judgements():
    env = TetrisEnv(batch=20, rules=TetrisRules(10, 12), seed=3)
    td = env.reset()
    oracle = OracleTrainer(frequency=1.0, consistency=0.8, seed=5)
    truth = oracle.judge(td, torch.zeros(20, dtype=torch.int64))
    agree = sum(
        float(v == t)
        for _ in range(200)
        for v, t in zip(
            _values(oracle.give(td, torch.zeros(20, dtype=torch.int64), 0.0, torch.zeros(20))),
            truth,
            strict=True,
        )
    )
    assert abs(agree / 4000 - 0.8) < 0.032  # s.d. 0.0063


def _hand_obs(rows: list[str], piece: str) -> TensorDict:
    """One board from strings (top row first, '#' filled) and the current piece."""
    cells = torch.tensor([[ch == "#" for ch in r] for r in reversed(rows)])
    return TensorDict(
        {
            keys.BOARD: cells.unsqueeze(0),
            keys.PIECE: torch.tensor([PIECE_NAMES.index(piece)]),
            keys.PIECES_PLACED: torch.tensor([[4]]),
        },
        batch_size=[1],
    )


def _placement(piece: str, width: int, orient_width: int, column: int) -> int:
    t = placement_table(width)
    p = PIECE_NAMES.index(piece)
    return next(
        a
        for a in range(int(t.num_actions[p]))
        if t.piece_width[p, a] == orient_width and t.column[p, a] == column
    )


def test_value_proxy_signs_on_hand_made_boards():
    proxy = ValueProxyTrainer()
    empty = ["." * 10] * 6
    # an S flat on the floor leaves a hole under its right end: holes +1 (-4), transitions +4, a well +1
    s_flat = _placement("S", 10, 3, 0)
    assert proxy.value_change(_hand_obs(empty, "S"), torch.tensor([s_flat])).item() == -9.0
    (ev,) = proxy.give(_hand_obs(empty, "S"), torch.tensor([s_flat]), 2.0, torch.tensor([1]))[0]
    assert (ev.value, ev.time, ev.step, ev.episode, ev.source) == (-1.0, 2.3, 4, 1, "simulated:value_proxy")
    # a vertical I into a 2-deep well at the wall clears both rows and removes the well (wells 3 -> 0)
    well = ["." * 10] * 4 + [".#########"] * 2
    i_vertical = _placement("I", 10, 1, 0)
    assert proxy.value_change(_hand_obs(well, "I"), torch.tensor([i_vertical])).item() == 3.0
    assert _values(proxy.give(_hand_obs(well, "I"), torch.tensor([i_vertical]), 0.0, torch.tensor([0]))) == [
        1.0
    ]
    # an O into a 2x2 gap at the wall clears two rows and leaves an empty board: no change, no feedback
    gap = ["." * 10] * 4 + ["..########"] * 2
    assert proxy.give(_hand_obs(gap, "O"), torch.tensor([0]), 0.0, torch.tensor([0])) == [[]]
    scaled = ValueProxyTrainer(mode="scaled", scale=0.5)
    assert _values(scaled.give(_hand_obs(well, "I"), torch.tensor([i_vertical]), 0.0, torch.tensor([0]))) == [
        1.5
    ]


def test_gamma_sampler_matches_the_density():
    g = torch.Generator().manual_seed(0)
    x = sample_gamma(2.0, 0.28, 20_000, g)
    # mean 0.56, s.d. 0.28 * sqrt(2) = 0.396: s.e. of the mean 0.0028 (tolerance 0.015 > 5 s.e.)
    assert abs(float(x.mean()) - 0.56) < 0.015
    assert abs(float(x.std()) - 0.28 * math.sqrt(2)) < 0.015
    # P(x <= 0.28) = 1 - 2 / e = 0.2642 (s.e. 0.0031)
    assert abs(float((x <= 0.28).double().mean()) - (1 - 2 / math.e)) < 0.015
    small = sample_gamma(0.5, 2.0, 20_000, g)  # shape < 1 path: mean 1.0, s.e. 0.01
    assert abs(float(small.mean()) - 1.0) < 0.05 and (small > 0).all()


def _torch_marsaglia_tsang(shape: float, scale: float, n: int, g: torch.Generator) -> torch.Tensor:
    """The sampler written in torch ops throughout: what the numpy acceptance test must reproduce."""
    k = shape + 1.0 if shape < 1.0 else shape
    d = k - 1.0 / 3.0
    c = 1.0 / math.sqrt(9.0 * d)
    out, todo = torch.empty(n, dtype=torch.float64), torch.arange(n)
    while todo.numel() > 0:
        x = torch.randn(todo.numel(), generator=g, dtype=torch.float64)
        u = torch.rand(todo.numel(), generator=g, dtype=torch.float64)
        v = (1.0 + c * x) ** 3
        ok = (v > 0) & (torch.log(u) < 0.5 * x * x + d - d * v + d * torch.log(v.clamp_min(1e-300)))
        out[todo[ok]] = d * v[ok]
        todo = todo[~ok]
    if shape < 1.0:
        out = out * torch.rand(n, generator=g, dtype=torch.float64) ** (1.0 / shape)
    return out * scale


@pytest.mark.parametrize("shape", [2.0, 0.5, 5.0])
def test_gamma_sampler_draws_what_the_torch_formula_draws(shape: float) -> None:
    """Same generator, same draws to the bit, and the generator left in the same state (the runs and
    feedback logs made before the numpy acceptance test stay reproducible)."""
    g1, g2 = torch.Generator().manual_seed(7), torch.Generator().manual_seed(7)
    for n in (1, 10, 37, 1, 5000):
        assert torch.equal(sample_gamma(shape, 0.28, n, g1), _torch_marsaglia_tsang(shape, 0.28, n, g2))
    assert torch.equal(g1.get_state(), g2.get_state())


def _obs_of_env(batch: int) -> TensorDict:
    return TetrisEnv(batch=batch, rules=TetrisRules(10, 12), seed=0).reset()


def test_timing_delays_follow_the_gamma_density():
    td = _obs_of_env(20)
    timing = HumanLikeTiming(OracleTrainer(1.0, 1.0), delay=GammaDelay(2.0, 0.28), seed=1)
    delays = []
    for k in range(100):
        for evs in timing.give(td, torch.zeros(20, dtype=torch.int64), 10.0 * k, torch.zeros(20)):
            delays += [ev.time - 10.0 * k for ev in evs]
    d = torch.tensor(delays)
    assert len(d) == 2000 and (d > 0).all()
    assert abs(float(d.mean()) - 0.56) < 0.04  # s.e. 0.0089


def test_timing_absence_covers_whole_games():
    td = _obs_of_env(10)
    timing = HumanLikeTiming(OracleTrainer(1.0, 1.0), delay=0.1, absence=0.5, seed=3)
    counts = torch.zeros(10, 40, dtype=torch.int64)
    for game in range(40):
        for k in range(5):
            ev = timing.give(td, torch.zeros(10, dtype=torch.int64), 50.0 * game + k, torch.full((10,), game))
            counts[:, game] += torch.tensor([len(e) for e in ev])
    assert set(counts.unique().tolist()) <= {0, 5}  # all or nothing within a game
    away = (counts == 0).double().mean()
    assert abs(float(away) - 0.5) < 0.1  # 400 games: s.d. 0.025


def test_timing_fatigue_and_positive_bias():
    td = _obs_of_env(20)
    tired = HumanLikeTiming(OracleTrainer(1.0, 1.0), delay=0.1, fatigue_tau=50.0, seed=4)
    rate = torch.zeros(200)
    for t in range(200):
        rate[t] = (
            sum(len(e) for e in tired.give(td, torch.zeros(20, dtype=torch.int64), float(t), torch.zeros(20)))
            / 20
        )
    expect = torch.exp(-torch.arange(200.0) / 50.0)
    for lo, hi in ((0, 20), (50, 80), (150, 200)):
        assert abs(float(rate[lo:hi].mean() - expect[lo:hi].mean())) < 0.05  # >= 600 draws: s.d. <= 0.02
    nice = HumanLikeTiming(OracleTrainer(1.0, 0.0), delay=0.1, positive_bias=1.0, bias_to="positive", seed=0)
    quiet = HumanLikeTiming(OracleTrainer(1.0, 0.0), delay=0.1, positive_bias=1.0, bias_to="silence", seed=0)
    a = torch.zeros(20, dtype=torch.int64)
    truth = OracleTrainer().judge(td, a)
    assert _values(nice.give(td, a, 0.0, torch.zeros(20))) == [1.0] * 20
    assert _values(quiet.give(td, a, 0.0, torch.zeros(20))) == [1.0 if t < 0 else None for t in truth]


def test_timing_tails_off_as_lines_rise():
    td = _obs_of_env(2)
    timing = HumanLikeTiming(OracleTrainer(1.0, 1.0), delay=0.1, tail_lines=20.0, seed=5)
    timing.give(td, torch.zeros(2, dtype=torch.int64), 0.0, torch.zeros(2))
    timing.end_games(torch.tensor([True, True]), torch.tensor([180, 0]))
    given = torch.zeros(2)
    for k in range(1, 1001):
        given += torch.tensor(
            [len(e) for e in timing.give(td, torch.zeros(2, dtype=torch.int64), k, torch.ones(2))]
        )
    assert abs(float(given[0]) / 1000 - 0.1) < 0.04  # 20 / (20 + 180); s.d. 0.0095
    assert given[1] == 1000


def test_replay_reproduces_a_log_on_the_same_steps(tmp_path, run_learner):
    over = ["agent=tamer", "domain.width=8", "domain.height=8", "agent.games=3", "human.alpha=0.002"]
    over += [
        "agent.learners=2",
        "seed=7",
        "domain.max_pieces=200",
        "trainer.reaction=0.2",
        "trainer.timing.enabled=false",
    ]
    first, _ = run_learner(tmp_path / "first", *over, "trainer=oracle", "trainer.consistency=0.8")
    recorded = load_feedback_log(tmp_path / "first" / "feedback.jsonl")
    assert len(recorded) == int(first.given[..., 0].sum()) > 0
    log = tmp_path / "first" / "feedback.jsonl"
    second, _ = run_learner(tmp_path / "second", *over, "trainer=replay", f"trainer.log={log}")
    replayed = load_feedback_log(tmp_path / "second" / "feedback.jsonl")
    assert torch.equal(first.lines, second.lines)
    assert torch.equal(first.human.model.weight, second.human.model.weight)

    def key(e: FeedbackEvent) -> tuple:
        return (e.session.split("/")[-1], e.episode, e.step, e.value, round(e.time, 6))

    assert sorted(map(key, replayed)) == sorted(map(key, recorded))
    assert {e.source for e in replayed} == {"replay"} and {e.source for e in recorded} == {"simulated:oracle"}


def test_queue_trainer_labels_events_from_a_producer_thread():
    queue = FeedbackQueue()
    trainer = QueueTrainer(queue, board=1)
    td = _obs_of_env(2)
    ready, go = threading.Event(), threading.Event()
    script = {1: [(0.5, 1.0)], 2: [(1.2, -1.0), (1.9, 1.0)], 3: []}  # placement k happens at time k - 1

    def producer() -> None:
        for k in (1, 2, 3):
            go.wait()
            go.clear()
            for t, v in script[k]:
                queue.put(FeedbackEvent(time=t, value=v, source="human:browser"))
            ready.set()

    thread = threading.Thread(target=producer)
    thread.start()
    got = []
    episode = torch.tensor([0, 3])
    for k in range(4):
        if k > 0:
            go.set()
            assert ready.wait(timeout=5.0)
            ready.clear()
        td[keys.PIECES_PLACED] = torch.tensor([[0], [k]])
        events = trainer.give(td, torch.zeros(2, dtype=torch.int64), float(k), episode)
        assert events[0] == []
        got += events[1]
    thread.join(timeout=5.0)
    assert [(e.time, e.value, e.episode, e.step, e.source) for e in got] == [
        (0.5, 1.0, 3, 0, "human:browser"),
        (1.2, -1.0, 3, 1, "human:browser"),
        (1.9, 1.0, 3, 1, "human:browser"),
    ]
    queue.put(FeedbackEvent(time=-1.0, value=1.0, source="human:browser"))  # older than every placement
    (late,) = trainer.give(td, torch.zeros(2, dtype=torch.int64), 4.0, episode)[1]
    assert (late.step, late.episode) == (-1, -1)


def test_every_trainer_logs_every_event(tmp_path):
    td = _obs_of_env(3)
    queue = FeedbackQueue()
    prior = [FeedbackEvent(time=0.0, value=1.0, source="simulated:oracle", step=0, episode=0)]
    makers = {
        "oracle": lambda log: OracleTrainer(0.7, 0.8, seed=1, log=log),
        "value_proxy": lambda log: ValueProxyTrainer(log=log),
        "timing": lambda log: HumanLikeTiming(OracleTrainer(1.0, 0.5), log=log),
        "replay": lambda log: ReplayTrainer(prior, log=log),
        "queue": lambda log: QueueTrainer(queue, log=log),
    }
    for name, make in makers.items():
        with FeedbackLog(tmp_path / f"{name}.jsonl", name, fsync=False) as log:
            trainer = make(log)
            given = []
            for k in range(5):
                queue.put(FeedbackEvent(time=k - 0.5, value=-1.0, source="human:browser"))
                for evs in trainer.give(td, torch.full((3,), k), float(k), torch.zeros(3)):
                    given += evs
        logged = load_feedback_log(tmp_path / f"{name}.jsonl")
        assert len(given) > 0, name
        assert logged == given, name
        assert {e.session for e in logged} <= {f"{name}/board{b}" for b in range(3)}
