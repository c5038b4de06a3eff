"""A keepaway run stopped or killed and resumed is the uninterrupted run: its checkpoint holds everything in
flight (the simulator's fields and generator, the env's bookkeeping, the keepers' pending transitions, H^'s
credit windows, the trainer's and the fusion's draws, the episodes in progress)."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.common.checkpoint import CheckpointWarning, load_checkpoint
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawayEnv
from hfrl_torch.envs.keepaway.simulator import KeepawaySimulator
from hfrl_torch.models.tile_coding import TileCoding

SMALL = [
    "domain=keepaway",
    "agent.learners=2",
    "agent.table_bits=12",
    "agent.log_minutes=0.05",
    "agent.log_episodes=1",
    "agent.hours=0.004",
    "agent.checkpoint_minutes=0.05",
    "seed=3",
]
TAUGHT = ["trainer=oracle", "fusion=linear"]
WALL_CLOCK = "field_cycles_per_s"  # a throughput measured in wall time: differs between any two runs


def _metrics(run_dir) -> list[dict]:
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    for r in rows:
        r.pop(WALL_CLOCK, None)
    return rows


def _events(run_dir) -> list[str]:
    """The logged events without their session (a resumed log holds a second session header)."""
    lines = (run_dir / "feedback.jsonl").read_text().splitlines()
    return [e.split('"session"')[0] for e in lines if '"schema"' not in e]


def _assert_same_run(whole, part, whole_dir, part_dir) -> None:
    assert _metrics(whole_dir) == _metrics(part_dir) and len(_metrics(whole_dir)) >= 4
    assert torch.equal(whole.agent_sarsa.coder.weight, part.agent_sarsa.coder.weight)
    assert torch.equal(whole.records.table, part.records.table)
    assert torch.equal(whole.records.clock, part.records.clock)
    if whole.taught:
        assert torch.equal(whole.tamer.model.weight, part.tamer.model.weight)
        assert _events(whole_dir) == _events(part_dir) and len(_events(whole_dir)) > 5
        assert torch.equal(whole.fusion.weight(), part.fusion.weight())


@pytest.mark.parametrize("kernels", ["auto", "cycle"])
def test_a_stopped_and_resumed_run_equals_the_uninterrupted_one(tmp_path, run_learner, one_thread, kernels):
    """With either CPU path: ``cycle``'s per-field random streams are in the checkpoint too."""
    small = [*SMALL, f"domain.kernels={kernels}"]
    whole, _ = run_learner(tmp_path / "whole", *small)
    _, stopped = run_learner(tmp_path / "part", *small, stop_after=3)
    ckpt = load_checkpoint(tmp_path / "part")
    # (a step that closes several points logs them all before the stop: one step advances every field
    # to its next decision on the cycle path)
    assert stopped is None and 3 <= len(ckpt["history"]) < len(whole.history)
    assert int(ckpt["state"]["play"]["env"]["sim"]["state"]["episode_cycles"].max()) > 0  # mid-episode
    part, final = run_learner(tmp_path / "part", *small, checkpoint=ckpt)
    assert final is not None and load_checkpoint(tmp_path / "part")["state"]["resumes"] == 1
    _assert_same_run(whole, part, tmp_path / "whole", tmp_path / "part")


def test_a_taught_run_killed_after_its_checkpoint_resumes_to_the_uninterrupted_run(
    tmp_path, run_learner, one_thread
):
    """Stopped at 2 points and resumed (Ctrl-C), stopped again at 4, then put back to the checkpoint of 2
    points, as a kill after that checkpoint leaves it: the log already holds the events given after it, which
    the trainer gives again on resume; each is learned once and logged once."""
    over = [*SMALL, *TAUGHT]
    whole, _ = run_learner(tmp_path / "whole", *over)
    part = tmp_path / "part"
    run_learner(part, *over, stop_after=2)
    logged = len(_events(part))
    early = part / "checkpoints" / "early.pt"
    shutil.copy(part / "checkpoints" / "last.pt", early)
    ckpt = load_checkpoint(part)
    assert int(ckpt["state"]["play"]["tamer"]["filled"].sum()) > 0  # credit windows in flight
    run_learner(part, *over, stop_after=4, checkpoint=ckpt)
    assert len(_events(part)) > logged and 4 <= len(load_checkpoint(part)["history"]) < len(whole.history)
    shutil.copy(early, part / "checkpoints" / "last.pt")
    resumed, final = run_learner(part, *over, checkpoint=load_checkpoint(part))
    assert final is not None and resumed.log.matched > 0  # given again, found in the log, not rewritten
    _assert_same_run(whole, resumed, tmp_path / "whole", part)


def test_a_checkpoint_without_the_play_in_progress_loads_with_a_warning(tmp_path, run_learner, one_thread):
    run_learner(tmp_path, *SMALL, *TAUGHT, stop_after=2)
    ckpt = load_checkpoint(tmp_path)
    del ckpt["state"]["play"]  # what a checkpoint written before the play was saved holds
    with pytest.warns(CheckpointWarning, match="predates saved episodes in progress"):
        learner, final = run_learner(tmp_path, *SMALL, *TAUGHT, checkpoint=ckpt)
    assert final is not None and int(learner.records.learner_clock.min()) >= 0.004 * 36000


def test_a_play_that_does_not_fit_is_one_line(tmp_path, run_learner, one_thread):
    run_learner(tmp_path, *SMALL, stop_after=1)
    ckpt = load_checkpoint(tmp_path)
    ckpt["state"]["play"]["env"]["sim"]["state"]["pos"] = torch.zeros(1, 6, 2)
    with pytest.raises(CheckpointError, match="does not continue this keepaway run's play") as info:
        run_learner(tmp_path, *SMALL, checkpoint=ckpt)
    assert "\n" not in str(info.value)


def test_the_env_continues_from_its_state_as_if_never_saved():
    env = KeepawayEnv(3, KeepawayConfig(**TASKS["exact"]), seed=5, sync="any")
    td = env.reset()
    actions = torch.zeros(3, dtype=torch.int64)
    for _ in range(20):
        td["action"] = actions
        td, td = env.step_and_maybe_reset(td)
    saved = env.state_dict()
    again = KeepawayEnv(3, KeepawayConfig(**TASKS["exact"]), seed=99, sync="any")
    again.load_state_dict(saved)
    for _ in range(40):
        td["action"] = actions
        out, td = env.step_and_maybe_reset(td)
        out2, _ = again.step_and_maybe_reset(out.exclude("next").clone())
        assert (out["next"] == out2["next"]).all()
    for name, value in env.sim.state.tensors().items():
        assert torch.equal(value, again.sim.state.tensors()[name]), name
    with pytest.raises(ValueError, match="keepaway env output 'observation' does not fit"):
        KeepawayEnv(2, KeepawayConfig(**TASKS["exact"])).load_state_dict(saved)


def _coder() -> TileCoding:
    return TileCoding([1.0] * 13, num_actions=3, learners=2, tilings=4, size=2**8)


def test_the_simulator_and_keeper_tamer_round_trip_their_state():
    sim = KeepawaySimulator(2, KeepawayConfig(**TASKS["exact"]), seed=1)
    for _ in range(7):
        sim.step(torch.zeros(2, dtype=torch.int64))
    copy = KeepawaySimulator(2, KeepawayConfig(**TASKS["exact"]), seed=2)
    copy.load_state_dict(sim.state_dict())
    for _ in range(30):
        a, b = sim.step(torch.zeros(2, dtype=torch.int64)), copy.step(torch.zeros(2, dtype=torch.int64))
        assert torch.equal(a.ended, b.ended)
    assert torch.equal(sim.state.pos, copy.state.pos) and torch.equal(sim.state.seen_pos, copy.state.seen_pos)
    with pytest.raises(ValueError, match="keepaway simulator state 'pos'"):
        KeepawaySimulator(3, KeepawayConfig(**TASKS["exact"])).load_state_dict(sim.state_dict())

    tamer = KeeperTamer(_coder(), fields=2)
    tiles = torch.randint(0, 2**8, (2, tamer.model.active_tiles), generator=torch.Generator().manual_seed(0))
    tamer.record(torch.tensor([True, False]), torch.tensor([0, 1]), tiles, torch.tensor([1.0, 1.0]))
    other = KeeperTamer(_coder(), fields=2)
    other.load_state_dict(tamer.state_dict())
    times, values = torch.tensor([1.3, 1.3]), torch.tensor([1.0, -1.0])
    assert tamer.give(values, times) == other.give(values, times) == 1
    assert torch.equal(tamer.model.weight, other.model.weight) and other.decisions == 1
    with pytest.raises(ValueError, match="KeeperTamer state 'tiles'"):
        KeeperTamer(_coder(), fields=3).load_state_dict(tamer.state_dict())
