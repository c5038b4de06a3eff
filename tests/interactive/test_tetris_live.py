"""Tetris in the browser trainer: the frames (a placement's cells, the rows it clears), presses filed under
the placement on screen the reaction allowance before them and credited to it, and the taught CE loop."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable

import aiohttp
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.envs.tetris.env import TetrisEnv
from hfrl_torch.envs.tetris.pieces import placement_table
from hfrl_torch.envs.tetris.rules import TetrisRules
from hfrl_torch.experiment import factories
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.feedback.credit import PreviousStep, credit_weights
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight
from hfrl_torch.interactive.live import LiveTeaching, saved_run
from hfrl_torch.interactive.messages import Feedback, Presence
from hfrl_torch.interactive.server import TeachingServer
from hfrl_torch.interactive.session import CONDITION_FIELDS, NotTaken, TeachingSession
from hfrl_torch.interactive.tetris_live import BrowserTetrisTrainer, TetrisPage, landing, tetris_frame


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), choices=st.lists(st.integers(0, 10**6), min_size=30, max_size=30))
def test_frames_show_where_the_piece_landed_and_the_rows_it_cleared(seed, choices):
    env = TetrisEnv(batch=1, rules=TetrisRules(width=6, height=8), features="bt", max_pieces=30)
    env.set_seed(seed)
    td = env.reset()
    table = placement_table(6)
    for choice in choices:
        legal = td[keys.ACTION_MASK][0].nonzero().flatten()
        td[keys.ACTION] = legal[choice % len(legal)].view(1)
        td = env.step(td)
        frame = tetris_frame(td, episode=0, weight=0.5)
        before, after = td[keys.BOARD][0], td["next", keys.BOARD][0]
        cells = landing(before, int(td[keys.PIECE][0]), int(td[keys.ACTION][0]), table)
        full = before.clone()
        for r, c in cells:
            if r < full.shape[0]:
                assert not before[r, c]  # the piece lands on free cells
                full[r, c] = True
        rows = [r for r in range(full.shape[0]) if bool(full[r].all())]
        kept = full[[r for r in range(full.shape[0]) if r not in rows]]
        expected = torch.cat([kept, torch.zeros(len(rows), full.shape[1], dtype=torch.bool)])
        if not bool(td["next", keys.DONE].any()):
            assert torch.equal(expected, after)  # the engine's board: the full rows removed
        assert frame["cleared"] == len(rows) and frame["cleared_rows"] == rows
        if rows:
            assert frame["before_clear"] == full.to(torch.int64).tolist() and frame["placed"] == []
        else:
            assert frame["placed"] == cells and frame["before_clear"] is None
        if bool(td["next", keys.DONE].any()):
            break
        td = td["next"]


def _fake(start: float = 0.0) -> tuple[list[float], TeachingSession]:
    clock = [start]
    return clock, TeachingSession(actions_per_s=4.0, clock=lambda: clock[0], sleep=lambda s: None)


def test_a_press_is_credited_to_the_placement_on_screen_the_allowance_before_it(tmp_path):
    clock, session = _fake()
    log = FeedbackLog(tmp_path / "feedback.jsonl", session="t")
    trainer = BrowserTetrisTrainer(session, log)
    starts = [0.0, 0.25, 0.5, 0.75]  # four placements at 4 a second: faster than the 0.3 s allowance
    for k, t in enumerate(starts):
        clock[0] = t
        session.shown(t, episode=2, step=k, label=f"placement {k + 1}")
    clock[0] = 0.9  # 0.3 s before: 0.6, placement 3 on screen (placement 4 is on screen at the press)
    assert session.apply(Feedback(1.0))["filed"] == "placement 3"
    clock[0] = 1.0
    obs = {keys.PIECES_PLACED: torch.tensor([4])}
    events = trainer.give(TensorDict(obs, batch_size=[1]), torch.zeros(1), 1.0, torch.tensor([2]))[0]
    assert [(e.step, e.episode) for e in events] == [(2, 2)]
    assert 0.5 < events[0].time <= 0.75  # min(0.5 + 0.3, the next placement's start 0.75, now)
    credit = credit_weights(
        events[0].time, torch.tensor(starts), torch.tensor([*starts[1:], 1.0]), PreviousStep()
    )
    assert credit.tolist() == [0.0, 0.0, 1.0, 0.0]  # all of it to placement 3, the one filed under
    clock[0] = 1.4  # after the game's last placement: 0.3 s before is 1.1, placement 4
    session.apply(Feedback(-1.0))
    late = trainer.late(1.5)[0]
    assert [(e.step, e.value) for e in late] == [(3, -1.0)] and late[0].time == 1.05
    session.queue.put(FeedbackEvent(time=1.45, value=1.0, source="human:browser"))  # acknowledged, then stop
    teaching = LiveTeaching(TeachingServer(session, port=0), session, trainer)
    assert teaching.stop("stopped") == 1
    log.close()
    logged = load_feedback_log(tmp_path / "feedback.jsonl")
    assert [(e.step, e.episode) for e in logged] == [(2, 2), (3, 2), (3, 2)] and trainer.given == 3


def test_the_page_is_told_rounds_games_and_what_is_left():
    _, session = _fake()
    wall = [10.0]
    page = TetrisPage(session, rounds=4, clock=lambda: wall[0])
    assert not session.live  # nothing to judge before the first game
    page.start_game(0)
    assert not session.live and page.games == 1  # nor before its first placement
    env = TetrisEnv(batch=1, rules=TetrisRules(width=6, height=12), features="bt", max_pieces=30)
    td = env.reset()
    page.placed(env.step(td.set(keys.ACTION, td[keys.ACTION_MASK].to(torch.int64).argmax(-1))), 0, 0.0, 0.5)
    assert session.live
    page.practising(0)
    assert not session.live and session.latest()[1] == {  # the person's game is over: said with its lines
        "type": "status",
        "phase": "practice",
        "round": 1,
        "rounds": 4,
        "game_over": {"game": 1, "lines": 0},
    }
    wall[0] = 16.0
    page.point(0, 3.5, taught=True)
    wall[0] = 18.0
    page.practising(1)
    assert "game_over" not in session.latest()[1]  # a round alone: no game of the person's ended
    page.point(1, 5.0, taught=False)
    assert session.curve == [[1.0, 3.5, 1.0], [2.0, 5.0, 0.0]]
    # no page is open: the rounds to come practise alone, at the 2 s the one alone took
    assert session.progress == {"unit": "rounds", "done": 2, "total": 4, "left": 2, "left_s": 2 * 2.0}


def test_the_time_left_follows_whether_the_person_teaches():
    """Once said: "49 of 50 practice rounds left, about 33 min 22 s" while the person was away and the
    rounds ran alone in 40 s. A watched round lasts a paced game, one alone a moment."""
    _, session = _fake()
    wall = [0.0]
    page = TetrisPage(session, rounds=10, clock=lambda: wall[0])
    session.connect()
    page.start_game(0)
    wall[0] = 40.0
    page.point(0, 2.0, taught=True)  # the person watched a 40 s game
    assert session.progress["left_s"] == 9 * 40.0
    session.apply(Presence(False))  # "I'm away"
    page.practising(1)
    assert session.progress["left_s"] is None  # no round alone measured yet: no guess
    wall[0] = 40.8
    page.point(1, 2.0, taught=False)
    assert session.progress["left_s"] == pytest.approx(8 * 0.8)
    session.apply(Presence(True))
    page.start_game(2)
    assert session.progress["left_s"] == 8 * 40.0


def test_a_taught_ce_round_files_each_press_under_the_placement_shown_before_it(
    tmp_path, monkeypatch, run_learner
):
    clock, session = _fake()
    presses = [(1.1, 1.0), (1.6, -1.0), (2.35, 1.0)]  # wall times; 4 placements a second from 0.0

    def sleep(s: float) -> None:  # the person presses while the agent plays
        clock[0] += s
        while presses and presses[0][0] <= clock[0]:
            session.apply(Feedback(presses.pop(0)[1]))

    session.sleep = sleep
    session.connect()
    made = {}

    def live(cfg, view, fusion, drain, *page):  # page: the starting speed and words, unused here
        made["teaching"] = LiveTeaching(TeachingServer(session, port=0), session, drain(session))
        return made["teaching"]

    monkeypatch.setattr(factories, "make_live_teaching", live)
    over = ["trainer=interactive", "trainer.wait_for_page_s=0", "agent.iterations=1", "agent.population=6"]
    over += ["agent.games_per_candidate=1", "agent.eval_games=2", "agent.watch_pieces=30", "domain.height=20"]
    learner, final = run_learner(tmp_path, *over)
    assert not presses and final["feedback/given"] == 3 and float(learner.human.applied.sum()) == 3
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    # pressed at 1.25, 1.75, 2.5 (the sleep that passes each time), filed under what was on screen 0.3 s
    # before: placements 3, 5, 8 (0-based, at 0.75, 1.25, 2.0), one earlier than on screen at the press
    assert [(e.step, e.episode, e.value) for e in events] == [(3, 0, 1.0), (5, 0, -1.0), (8, 0, 1.0)]
    assert [e.time for e in events] == [1.0, 1.5, 2.25]  # capped at the next placement's start
    assert session.curve == [[1.0, final["eval/mean_policy_lines_mean"], 1.0]]
    assert session.ending == "stopping" and session.queue.closed  # closed by the loop, as after a run


def test_the_page_counts_the_moves_the_teaching_changed(tmp_path):
    _, session = _fake()
    page = TetrisPage(session, rounds=2)
    env = TetrisEnv(batch=1, rules=TetrisRules(width=6, height=12), features="bt", max_pieces=30)
    td = env.reset()
    page.start_game(0)
    for alone in [None, 4, None]:
        action = td[keys.ACTION_MASK].to(torch.int64).argmax(-1)
        td.set(keys.ACTION, action)
        td = env.step(td)
        page.placed(td, 0, 0.0, weight=0.5, alone=alone)
        frame = session.latest()[1]
        assert (frame["without_you"] is None) == (alone is None)
        td = td["next"]
    assert frame["steered"] == [1, 3] and session.latest()[1]["without_you"] is None
    page.start_game(1)
    page.placed(env.step(td.set(keys.ACTION, td[keys.ACTION_MASK].to(torch.int64).argmax(-1))), 1, 0.0, 0.5)
    assert session.latest()[1]["steered"] == [0, 1]  # counted per game


async def _watch_and_press(
    url: str, origin: str, page: TetrisPage, td: TensorDict, end: Callable[[], object]
) -> list[dict]:
    """Every message one page gets: the opening ones, a placement, a press's ack, the curve and ``end``'s."""
    got: list[dict] = []
    async with aiohttp.ClientSession() as client, client.ws_connect(url, origin=origin) as ws:
        got += [json.loads((await ws.receive(timeout=10)).data) for _ in range(3)]  # config, settings, role
        page.start_game(0)
        page.placed(td, 0, time.time(), weight=0.37, alone=None)
        while not any(m["type"] == "tetris" for m in got):
            got.append(json.loads((await ws.receive(timeout=10)).data))
        page.point(0, 2.0, taught=True)
        await asyncio.sleep(0.5)  # the placement is on the page the reaction allowance before the press
        await ws.send_str('{"type": "feedback", "value": 1, "id": 1}')
        ending = None
        async for msg in ws:
            got.append(json.loads(msg.data))
            if got[-1]["type"] == "ack":
                ending = asyncio.ensure_future(asyncio.to_thread(end))
        assert ending is not None
        await ending
    return got


@pytest.mark.parametrize("blind", [True, False])
def test_a_blind_run_sends_nothing_that_names_its_condition(tmp_path, blind):
    """A study's participant must not learn their condition, not even from the browser's developer tools:
    with trainer.blind no message of the run carries the fusion's name, its scheme or the weight on H^."""
    over = ["trainer=interactive", "trainer.port=0", f"trainer.blind={str(blind).lower()}"]
    cfg = compose_config("train", *over, "fusion=linear")
    fusion = Fusion.from_option("linear", ConstantWeight(0.37))
    teaching = factories.make_live_teaching(cfg, "tetris", fusion, lambda s: BrowserTetrisTrainer(s))
    server, session = teaching.server, teaching.session
    env = TetrisEnv(batch=1, rules=TetrisRules(width=6, height=12), features="bt", max_pieces=30)
    td = env.reset()
    td = env.step(td.set(keys.ACTION, td[keys.ACTION_MASK].to(torch.int64).argmax(-1)))
    url, origin = f"ws://127.0.0.1:{server.port}/ws", f"http://127.0.0.1:{server.port}"
    end = lambda: teaching.stop("finished", saved_run(tmp_path, "agent.iterations", 5))  # noqa: E731
    try:
        pressing = _watch_and_press(url, origin, TetrisPage(session, 2), td, end)
        got = asyncio.run(asyncio.wait_for(pressing, 30))
    finally:
        end()
    summary = json.loads((tmp_path / "teaching_summary.json").read_text())  # what the end message said
    types = {m["type"] for m in got}
    assert {"config", "settings", "role", "tetris", "ack", "curve"} <= types and summary["type"] == "end"
    text = json.dumps([*got, summary])
    named = [k for m in [*got, summary] for k in m if k in CONDITION_FIELDS]
    if blind:
        assert named == [] and "0.37" not in text and "linear" not in text and "fusion" not in text
        assert "weight" not in text.lower()
    else:  # the same run unblinded says all of it: the check above can fail
        assert {"weight", "weight_name", "weight_sentence"} <= set(named) and "0.37" in text


def test_no_press_is_taken_before_the_first_placement_is_on_screen():
    """Start-up: the first game begins, but its first placement waits for the learner (seconds of numba
    compiling on a fresh cache); a press then has nothing to judge and is refused, not filed at step -1."""
    clock, session = _fake(100.0)
    session.set_live(False)  # as make_live_teaching starts it
    page = TetrisPage(session, rounds=2)
    page.start_game(0)
    clock[0] = 105.0
    for on_screen in (None, -1, 0):  # 0: the "starting" status the page got on connecting
        with pytest.raises(NotTaken, match="the run is starting: nothing is on screen to judge yet"):
            session.apply(Feedback(1.0), on_screen=on_screen)
    assert session.taken == 0 and not session.settings()["live"] and len(session.queue) == 0
    env = TetrisEnv(batch=1, rules=TetrisRules(width=6, height=12), features="bt", max_pieces=30)
    td = env.reset()
    page.placed(env.step(td.set(keys.ACTION, td[keys.ACTION_MASK].to(torch.int64).argmax(-1))), 0, 105.0, 0.5)
    clock[0] = 105.5
    reply = session.apply(Feedback(1.0), on_screen=session.version)
    assert session.settings()["live"] and (reply["episode"], reply["step"]) == (0, 0)
