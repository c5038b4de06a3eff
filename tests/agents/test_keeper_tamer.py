"""TAMER keepers: gamma credit over the last 500 ms of a field's decisions, and the keepaway oracle."""

from __future__ import annotations

import pytest
import torch

from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.envs.keepaway.policies import hand_coded_actions
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.models.tile_coding import TileCoding
from hfrl_torch.trainers.keepaway_oracle import KeepawayOracle

SPEC_CREDITS = [0.115, 0.127, 0.130, 0.110, 0.050]  # decisions 0.4, 0.3, 0.2, 0.1, 0.0 s before the press


def _model(learners: int = 1) -> TileCoding:
    return TileCoding([1.0, 1.0], num_actions=2, learners=learners, tilings=4, size=2**16)


def test_one_press_credits_the_last_500_ms_of_decisions_by_the_gamma_density():
    model = _model()
    tamer = KeeperTamer(model, fields=1, alpha=1.0)
    states = torch.tensor([[0.0, 0.0], [10.0, 10.0], [20.0, 20.0], [30.0, 30.0], [40.0, 40.0]])
    tiles = model.tiles(states)[:, 0]  # action 0's tiles of five far-apart states: no shared tile
    for i in range(5):
        tamer.record(torch.tensor([True]), torch.tensor([0]), tiles[i : i + 1], torch.tensor([0.1 * i]))
    credited = tamer.give(torch.tensor([1.0]), torch.tensor([0.5]))
    assert credited == 5
    learned = model(torch.zeros(5, dtype=torch.int64), tiles)  # H^ = alpha * c_i * (1 - 0) per decision
    torch.testing.assert_close(learned, torch.tensor(SPEC_CREDITS, dtype=torch.float32), atol=1.5e-3, rtol=0)


def test_feedback_credits_whichever_model_acted_and_nothing_older_than_the_window():
    model = _model(learners=3)  # one H^ per keeper
    tamer = KeeperTamer(model, fields=2, alpha=1.0)
    tiles = model.tiles(torch.tensor([[0.0, 0.0], [50.0, 50.0], [90.0, 90.0]]))[:, 0]
    both = torch.tensor([True, True])
    # field 0: keeper 0 at 0 s (until 1 s), keeper 2 at 1 s (until 5 s), keeper 1 at 5 s; a press at 5.2 s
    tamer.record(both, torch.tensor([0, 0]), tiles[[0, 0]], torch.tensor([0.0, 0.0]))
    tamer.record(both, torch.tensor([2, 0]), tiles[[1, 1]], torch.tensor([1.0, 0.1]))
    tamer.record(both, torch.tensor([1, 0]), tiles[[2, 2]], torch.tensor([5.0, 0.2]))
    tamer.give(torch.tensor([-1.0, 0.0]), torch.tensor([5.2, 0.4]))  # field 1 gave nothing
    assert model(torch.tensor([1]), tiles[2:3]).item() < 0  # acted 0.2 s before the press
    assert model(torch.tensor([2]), tiles[1:2]).item() < 0  # its action lasted until 0.2 s before
    assert model(torch.tensor([0]), tiles[:2]).abs().sum() == 0  # ended 4.2 s before; field 1 gave nothing


def test_credited_share_counts_decisions_that_ever_got_credit():
    model = _model()
    tamer = KeeperTamer(model, fields=1, alpha=0.5, history=2)
    tiles = model.tiles(torch.tensor([[0.0, 0.0]]))[:, 0]
    for i in range(6):
        tamer.record(torch.tensor([True]), torch.tensor([0]), tiles, torch.tensor([2.0 * i]))
        if i % 2 == 0:  # 0.6 s after the decision: past the previous decision's window
            tamer.give(torch.tensor([1.0]), torch.tensor([2.0 * i + 0.6]))
    assert tamer.credited_share == pytest.approx(2 / 4)  # decisions 0-3 retired; 0 and 2 got credit


def test_oracle_judges_against_the_hand_coded_policy_and_logs(tmp_path):
    obs = torch.rand(64, 13, generator=torch.Generator().manual_seed(0)) * 10
    hand = hand_coded_actions(obs, 3, 2)
    action = torch.where(torch.arange(64) % 2 == 0, hand, (hand + 1) % 3)
    log = FeedbackLog(tmp_path / "feedback.jsonl", session="s")
    oracle = KeepawayOracle(3, 2, frequency=1.0, consistency=1.0, seed=1, log=log)
    values, times = oracle.give(obs, action, torch.ones(64, dtype=torch.bool), torch.full((64,), 10.0))
    log.close()
    assert torch.equal(values, torch.where(action == hand, 1.0, -1.0).to(torch.float64))
    assert bool((times > 10.0).all()) and oracle.given == 64
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert len(events) == 64 and events[0].source == "simulated:keepaway_oracle"
    silent = KeepawayOracle(3, 2, frequency=0.0)
    assert not silent.give(obs, action, torch.ones(64, dtype=torch.bool), torch.zeros(64))[0].any()
    flipped = KeepawayOracle(3, 2, frequency=1.0, consistency=0.0)
    assert torch.equal(
        flipped.give(obs, action, torch.ones(64, dtype=torch.bool), torch.zeros(64))[0], -values
    )
