"""The browser trainer on any Gymnasium task (``domain=gym agent=dqn|ppo|tamer trainer=interactive``), with a
scripted page: the frames are the task's own (PNG), every acknowledged press is in the feedback log exactly
once (filed under the step the page was told), pause and finish behave as on the other domains, and a task
that cannot show frames is one line before the run."""

from __future__ import annotations

import asyncio
import base64
import io
import json
import re
import threading
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
import torch
from PIL import Image
from tensordict import TensorDict

from hfrl_torch import keys
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.interactive.gym_live import GymWatcher, png_data_url
from hfrl_torch.interactive.journal import JOURNAL_NAME, read_journal
from hfrl_torch.interactive.session import TeachingSession

CARTPOLE = ("domain=gym", "domain.env_id=CartPole-v1", "agent=dqn")
HELPERS = "tests.interactive.gym_live_helpers"
PAGE = (
    "trainer=interactive",
    "trainer.port=0",
    "trainer.wait_for_page_s=60",
    "trainer.actions_per_s=20",
    "agent.boards=2",
    "agent.frames=100000",  # the page finishes the run
    "agent.eval_every=100000",
    "agent.eval_episodes=2",
)
LIVE = (*PAGE, "agent.steps_per_batch=4", "agent.learn_after=32")  # DQN's
FILED = re.compile(r"action [01] at step (\d+) of episode (\d+)")
OTHER_DOMAINS = re.compile(r"tetris|placement|line|keeper|taker|ball|column|practice round", re.IGNORECASE)


def _image(url: str) -> np.ndarray:
    assert url.startswith("data:image/png;base64,")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))))


async def _teach(url: str, presses: int = 14) -> dict[str, Any]:
    """Teach as a page would: wait for a frame, press Good and Bad, pause and press, resume, press, and
    finish at once (the last presses may still wait in the queue); returns what the run said. With fewer
    than 14 ``presses``: that many Good presses, then finish."""
    origin = url.split("/?")[0].rstrip("/")
    said: dict[str, Any] = {"frames": [], "acks": [], "errors": [], "end": None}
    async with aiohttp.ClientSession() as client, client.ws_connect(f"{origin}/ws", origin=origin) as ws:

        async def receive() -> dict[str, Any]:
            m = json.loads((await ws.receive(timeout=60)).data)
            if m["type"] == "gym":
                said["frames"].append(m)
            elif m["type"] == "config":
                said["config"] = m
            return m

        async def reply(kind: str) -> dict[str, Any]:
            while True:
                m = await receive()
                if m["type"] == "error" or (m["type"] == "ack" and m["message"] == kind):
                    return m

        async def press(n: int, value: int) -> None:
            await asyncio.sleep(0.06)  # under the 20 messages a second the page may send
            await ws.send_str(json.dumps({"type": "feedback", "value": value, "id": n}))
            m = await reply("feedback")
            (said["acks"] if m["type"] == "ack" else said["errors"]).append(m)

        while not said["frames"]:
            await receive()
        await asyncio.sleep(0.5)  # a press counts for the frame on screen 0.3 s before it
        for n in range(presses if presses < 14 else 0):
            await press(n, 1)
        for n in range(8 if presses == 14 else 0):
            await press(n, 1 if n % 3 else -1)
        if presses == 14:
            await ws.send_str(json.dumps({"type": "pause", "paused": True}))
            assert (await reply("pause"))["type"] == "ack"
            for n in range(8, 11):
                await press(n, -1)
            await ws.send_str(json.dumps({"type": "pause", "paused": False}))
            assert (await reply("pause"))["type"] == "ack"
            for n in range(11, 14):
                await press(n, 1)
        await ws.send_str(json.dumps({"type": "finish"}))
        while said["end"] is None:
            m = await receive()
            if m["type"] == "end":
                said["end"] = m
    return said


def _taught(
    run_learner: Any,
    run_dir: Path,
    presses: int,
    checkpoint: Any = None,
    task: tuple[str, ...] = CARTPOLE,
    before: Any = None,
    live: tuple[str, ...] = LIVE,
) -> tuple[Any, Any, dict]:
    """The learner run in ``run_dir`` on ``task`` with a scripted page (:func:`_teach`) in another thread;
    ``before(learner)`` is called first."""
    said: dict[str, Any] = {}
    threads: list[threading.Thread] = []

    def page(learner: Any) -> None:
        if before is not None:
            before(learner)

        def teach() -> None:
            try:
                said.update(asyncio.run(_teach(learner.teaching.url, presses)))
            except BaseException as e:  # the run must not go on for its whole budget
                said["failed"] = repr(e)
                learner.teaching.session.ending = "finishing"

        threads.append(threading.Thread(target=teach, daemon=True))
        threads[-1].start()

    learner, final = run_learner(run_dir, *task, *live, checkpoint=checkpoint, prepare=page)
    for thread in threads:  # the run may end before the page has read its last message
        thread.join(timeout=60)
    assert "failed" not in said, said.get("failed")
    return learner, final, said


def test_each_acknowledged_press_on_cartpole_is_logged_once_under_the_step_it_was_filed(
    run_learner, tmp_path, one_thread
) -> None:
    learner, final, said = _taught(run_learner, tmp_path, 14)
    assert final is not None and learner.frames > 0  # a finished run (not interrupted) that played
    acks, end = said["acks"], said["end"]
    assert said["errors"] == [] and len(acks) == 14
    assert end["reason"] == "finished_by_you" and end["given"] == 14 and (end["good"], end["bad"]) == (8, 6)
    assert [a["paused"] for a in acks] == [False] * 8 + [True] * 3 + [False] * 3

    # the log: each acknowledged press once, in order, filed as the page was told
    events = [e for e in load_feedback_log(tmp_path / "feedback.jsonl") if e.session.endswith("/browser")]
    assert [e.value for e in events] == [float(a["value"]) for a in acks]
    assert [(e.episode, e.step) for e in events] == [(a["episode"], a["step"]) for a in acks]
    assert [e.seq for e in events] == list(range(14)) and len({e.id for e in events}) == 14
    assert [e.source for e in events] == ["human:browser"] * 8 + ["human:browser:paused"] * 3 + [
        "human:browser"
    ] * 3
    assert len(read_journal(tmp_path / JOURNAL_NAME)) == 14
    for a in acks:  # "action 1 at step 12 of episode 3": the 1-based step and episode of what was filed
        m = FILED.fullmatch(a["filed"])
        assert m and (int(m[1]), int(m[2])) == (a["step"] + 1, a["episode"] + 1), a

    # credited where the oracle's judgement of the action filed under would be, r = 0.3 s after it on the
    # simulated clock, or at the loop's clock when it read the press, if that was earlier (a step boundary:
    # after a pause, a stall, or at the stop)
    action_time = {(f.episode, f.step): f.sim for f in learner.teaching.session.timeline}
    assert {(f["episode"] - 1, f["step"] - 1) for f in said["frames"]} <= set(action_time)
    for e in events:
        t = action_time[e.episode, e.step]
        at_step = e.time / 0.2 == pytest.approx(round(e.time / 0.2))
        assert t < e.time <= t + 0.3 + 1e-9 and (e.time == pytest.approx(t + 0.3) or at_step), (e, t)

    # the frames: the task's own rendering, in no other domain's words; the page's curve has its own axes
    frame = said["frames"][-1]
    assert _image(frame["image"]).shape == (400, 600, 3) and _image(frame["image"]).std() > 0
    # what the teaching changed: counted over every step of the episode so far, and said as an action
    assert all(f["steered"][1] == f["step"] and 0 <= f["steered"][0] <= f["step"] for f in said["frames"])
    assert {f["without_you"] for f in said["frames"]} <= {None, "action 0", "action 1"}
    words = [f["action"] for f in said["frames"]] + [a["filed"] for a in acks]
    words += [said["config"][k] for k in ("task", "curve_x", "curve_y", "curve_note", "weight_sentence")]
    assert not [w for w in words if OTHER_DOMAINS.search(w)], words
    assert said["config"]["view"] == "gym" and said["config"]["task"] == "CartPole-v1"
    assert end["resume"] == f"python train.py resume={tmp_path}"  # finished by the person: nothing to add
    assert (tmp_path / "teaching_summary.json").exists() and learner.teaching.session.ending == "finishing"

    # resumed: the presses are numbered on, and the watched board's episodes go on from where they were
    episodes = learner.watcher.episode
    again, _, more = _taught(run_learner, tmp_path, 1, checkpoint=load_checkpoint(tmp_path))
    events = [e for e in load_feedback_log(tmp_path / "feedback.jsonl") if e.session.endswith("/browser")]
    assert [e.seq for e in events] == list(range(15)) and more["end"]["given"] == 1
    assert events[-1].episode == more["acks"][0]["episode"] >= episodes and again.watcher.episode >= episodes


def _channel(learner: Any) -> Any:
    """The channel the learner's feedback waits in (TAMER's own, else the feedback transform's)."""
    return learner.channel if learner.agent == "tamer" else learner.feedback_transform.channel


@pytest.mark.parametrize(
    ("learner", "sentence"),
    [
        (("agent=tamer", "fusion=none"), "The agent acts on what it learned from your presses alone"),
        (("agent=ppo", "fusion=linear", "agent.steps_per_batch=4", "agent.minibatch_size=8"), "The weight w"),
    ],
    ids=["tamer", "ppo"],
)
def test_tamer_and_ppo_are_taught_from_the_page_and_a_resumed_run_learns_the_presses_it_had_not(
    run_learner, tmp_path, one_thread, learner, sentence
) -> None:
    """TAMER alone and PPO fused on CartPole from the page: every acknowledged press logged once, in order,
    H^ learning from them, the page's weight sentence true of the learner; resumed, the presses logged after
    the checkpoint (the queue's last, logged at the stop, and one as a killed run's journal recovery logs
    it) go to the resumed learner's channel, to be learned once, and the numbering goes on."""
    task = ("domain=gym", "domain.env_id=CartPole-v1", *learner)
    first, final, said = _taught(run_learner, tmp_path, 14, task=task, live=PAGE)
    acks = said["acks"]
    assert final is not None and said["errors"] == [] and len(acks) == 14
    assert said["end"]["reason"] == "finished_by_you" and said["end"]["given"] == 14
    events = [e for e in load_feedback_log(tmp_path / "feedback.jsonl") if e.session.endswith("/browser")]
    assert [e.value for e in events] == [float(a["value"]) for a in acks]
    assert [(e.episode, e.step) for e in events] == [(a["episode"], a["step"]) for a in acks]
    assert [e.seq for e in events] == list(range(14))
    assert said["config"]["weight_sentence"].startswith(sentence), said["config"]["weight_sentence"]
    assert first.events >= 1 and first.human.updates >= 1  # H^ learned from the presses the loop drained

    ckpt = load_checkpoint(tmp_path)
    state = ckpt["state"]
    saved = state["channel"] if first.agent == "tamer" else state["feedback"]["channel"]
    waiting = 0
    if saved is not None:
        channel = type(_channel(first))(first.boards)
        channel.load_state_dict(saved)
        waiting = channel.pending
    session = events[0].session
    seen = state["log_seq"].get(session, -1)
    with FeedbackLog(tmp_path / "feedback.jsonl", session=tmp_path.name) as log:  # recovered from a journal
        log.append(FeedbackEvent(0.0, 1.0, "human:browser", step=0, episode=0, session=session))
    queued: dict[str, int] = {}
    _, _, more = _taught(
        run_learner,
        tmp_path,
        1,
        checkpoint=ckpt,
        task=task,
        live=PAGE,
        before=lambda learner: queued.update(n=_channel(learner).pending),
    )
    assert queued["n"] == waiting + (14 - seen), (queued, waiting, seen)
    events = [e for e in load_feedback_log(tmp_path / "feedback.jsonl") if e.session.endswith("/browser")]
    assert [e.seq for e in events] == list(range(16)) and more["end"]["given"] == 1


def test_an_atari_game_taught_live_logs_each_press_and_its_cnn_h_hat_learns_from_them(
    run_learner, tmp_path, one_thread
) -> None:
    """Deep TAMER's task: ALE/Bowling-v5 taught from the page (``fusion=human_only``: H^ alone acts). The page
    shows the game's own screen; every acknowledged press is logged once; H^ is the CNN over the frames and
    its weights move with the presses."""
    pytest.importorskip("ale_py", reason="the Atari extra (ale-py) is not installed")
    bowling = (
        "domain=gym",
        "domain.env_id=ALE/Bowling-v5",
        "domain.max_episode_steps=300",  # short greedy evaluations (a game runs thousands of steps)
        "agent=dqn",
        "fusion=human_only",
        "agent.buffer_size=64",
        "human.buffer_size=256",
        "human.batch_size=8",
    )
    start: dict[str, torch.Tensor] = {}

    def remember(learner: Any) -> None:
        start.update({k: v.clone() for k, v in learner.human.model.state_dict().items()})

    learner, final, said = _taught(run_learner, tmp_path, 6, task=bowling, before=remember)
    assert final is not None and said["errors"] == [] and len(said["acks"]) == 6
    events = [e for e in load_feedback_log(tmp_path / "feedback.jsonl") if e.session.endswith("/browser")]
    assert [e.value for e in events] == [1.0] * 6 and [e.seq for e in events] == list(range(6))
    assert said["config"]["task"] == "ALE/Bowling-v5"
    frame = _image(said["frames"][-1]["image"])
    assert frame.shape[2] == 3 and frame.std() > 0  # the game's own screen
    # learned: the presses the loop drained before the finish (the last ones may still wait in the queue)
    assert type(learner.human.model).__name__ == "ActionCNN" and 1 <= learner.human.applied <= 6
    moved = [k for k, v in learner.human.model.state_dict().items() if not torch.equal(v, start[k])]
    assert moved  # H^ learned from the presses


def test_frames_larger_than_the_page_shows_are_scaled_down() -> None:
    big = np.zeros((1000, 1600, 3), dtype=np.uint8)
    big[:, :800] = 255
    small = _image(png_data_url(big))
    assert small.shape == (400, 640, 3) and small[:, :310].min() == 255 and small[:, 330:].max() == 0
    cartpole = np.full((400, 600, 3), 7, dtype=np.uint8)
    assert _image(png_data_url(cartpole)).shape == (400, 600, 3)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            (f"domain.make={HELPERS}:cartpole_without_frames",),
            f"domain.make='{HELPERS}:cartpole_without_frames' cannot be shown in the browser: it was made "
            "with render_mode=None; the browser trainer needs render_mode='rgb_array'",
        ),
        (
            ("domain.make=tests.experiment.gym_task_helpers:make_corridor",),
            "cannot be shown in the browser: it renders no RGB frames (its render modes: none)",
        ),
        (
            ("domain.make=tests.experiment.gym_task_helpers:make_countdown",),
            "cannot be shown in the browser: it returned a CountDown",
        ),
    ],
)
def test_a_task_without_rgb_frames_is_one_line_before_the_run(compose_train, overrides, message) -> None:
    with pytest.raises(ConfigError) as err:
        compose_train(*CARTPOLE, "trainer=interactive", *overrides)
    assert message in str(err.value) and "\n" not in str(err.value)
    compose_train(*CARTPOLE, "trainer=interactive", f"domain.make={HELPERS}:cartpole_with_frames")


def test_the_watcher_counts_the_steps_the_teaching_changed_per_episode():
    watcher = GymWatcher(TeachingSession(actions_per_s=5.0), seconds_per_step=0.2, total_steps=10)

    def step(action: int, fused: list[float], done: bool = False) -> None:
        td = TensorDict(
            {
                keys.ACTION: torch.tensor([action, 0]),
                keys.ENV_VALUES: torch.tensor([[2.0, 1.0], [0.0, 5.0]]),
                keys.FUSED_VALUES: torch.tensor([fused, [0.0, 0.0]]),
            },
            [2],
        )
        watcher._step(td, TensorDict({keys.DONE: torch.tensor([[done], [False]])}, [2]))

    step(1, [0.0, 3.0])  # the fused values chose 1 where Q alone prefers 0: the teaching changed it
    assert watcher.steered == [1, 1] and watcher.without_you == 0
    step(0, [1.0, 0.0])  # Q's own choice
    assert watcher.steered == [1, 2] and watcher.without_you is None
    step(1, [3.0, 0.0])  # an exploring move: not the teaching's
    assert watcher.steered == [1, 3] and watcher.without_you is None
    step(1, [0.0, 3.0], done=True)
    assert watcher.steered == [0, 0] and watcher.episode == 1  # counted per episode
