"""Keepers taught by a (simulated) trainer: fusion of Q and H^, the feedback queue, trust from hold time."""

from __future__ import annotations

import json

import pytest
import torch
from hydra import compose, initialize_config_dir

from hfrl_torch.agents.sarsa.fused_keepers import FusedKeepers
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.app import CONF_DIR, implied_overrides
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv
from hfrl_torch.experiment.evaluate import keepaway_config
from hfrl_torch.experiment.keepaway_sarsa import (
    KeepawayRecords,
    check_keepaway_feedback,
    make_sarsa_keepers,
    run_sarsa_keepers,
    train_sarsa,
)
from hfrl_torch.feedback.credit import PreviousStep
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.fusion.schedules import ConstantWeight, TrustWeight
from hfrl_torch.models.tile_coding import TileCoding
from hfrl_torch.trainers.keepaway_oracle import KeepawayOracle
from hfrl_torch.trainers.keepaway_replay import KeepawayReplay


def _cfg(*overrides: str):
    base = ["domain=keepaway", "agent=sarsa", "human=tile_coded", "trainer=oracle", "fusion=linear"]
    with initialize_config_dir(str(CONF_DIR), version_base=None):
        return compose("train", overrides=[*base, *overrides])


def _fused(scheme: str, weight, fields: int = 1, trainer: KeepawayOracle | None = None, **kw) -> FusedKeepers:
    model = TileCoding([1.0, 1.0], num_actions=3, learners=fields, tilings=4, size=2**12)
    tamer = KeeperTamer(model, fields, alpha=1.0, **kw)
    schedule = weight if not isinstance(weight, float) else ConstantWeight([weight] * fields)
    owners = torch.arange(fields * 3) // 3
    return FusedKeepers(scheme, schedule, tamer, trainer, 3, owners, scaling="decision")


def _choose(fk: FusedKeepers, q: list[float], h: list[float], mask=(True, True, True)) -> int:
    """The argmax of the fused values for one decision whose H^ is set to ``h``."""
    fk.tamer.values = lambda owner, tiles: torch.tensor([h], dtype=torch.float64)
    fused = fk.fuse(torch.tensor([0]), torch.tensor([0]), torch.tensor([mask]))
    values = fused(torch.tensor([q], dtype=torch.float64), torch.zeros(1, 3, 8, dtype=torch.int64))
    return int(values.masked_fill(~torch.tensor([mask]), -torch.inf).argmax())


def test_fusion_rules_choose_as_the_thesis_writes_them():
    q, h = [10.0, 8.0, 0.0], [-1.0, 1.0, 0.0]  # Q prefers hold, H^ the first pass
    assert _choose(_fused("none", 0.5), q, h) == 0
    assert _choose(_fused("human_only", 0.5), q, h) == 1
    # rescaled: Q -> [1, 0.8, 0], H^ -> [0, 1, 0.5]; linear 1 + w*0 vs 0.8 + w*1
    assert _choose(_fused("linear", 0.1), q, h) == 0
    assert _choose(_fused("linear", 0.5), q, h) == 1
    # exponential: R (1 + H^w): 1 * 1 vs 0.8 * 2 for any w > 0
    assert _choose(_fused("exponential", 0.5), q, h) == 1
    assert _choose(_fused("reward_shaping", 5.0), q, h) == 0  # shaping acts on the reward, not the choice
    assert _choose(_fused("control_sharing", 1.0), q, h) == 1
    assert _choose(_fused("control_sharing", 0.0), q, h) == 0
    assert _choose(_fused("linear", 100.0), q, h, mask=(True, False, False)) == 0  # only hold available


def test_match_rate_counts_only_decisions_where_h_prefers_an_action():
    fk = _fused("linear", 0.5)
    _choose(fk, [1.0, 0.0, 0.0], [0.0, 0.0, 0.0])  # H^ indifferent: not compared
    assert fk.compared.tolist() == [0]
    _choose(fk, [1.0, 0.0, 0.0], [0.5, 0.0, 0.0])  # agree
    _choose(fk, [1.0, 0.0, 0.0], [0.0, 0.5, 0.0])  # disagree
    assert fk.compared.tolist() == [2] and fk.matches.tolist() == [1]


def test_trust_follows_eq_4_4_on_hold_time_per_learner():
    trust = TrustWeight.from_initial(0.5, learners=2)
    fk = _fused("linear", trust, fields=2)
    fk.compared, fk.matches = torch.tensor([4, 0]), torch.tensor([1, 0])
    fk.end_episodes(torch.tensor([0, 1]), torch.tensor([6.0, 9.0]))
    # first episode: l1 = l2 -> (0.5 + 0.25) / 2; field 1 compared nothing: trust kept
    assert fk.schedule.value().tolist() == pytest.approx([0.375, 0.5])
    fk.compared, fk.matches = torch.tensor([2, 0]), torch.tensor([2, 0])
    fk.end_episodes(torch.tensor([0]), torch.tensor([3.0]))
    assert fk.schedule.value().tolist() == pytest.approx([(6 * 0.375 + 3 * 1.0) / 9, 0.5])
    assert fk.compared.tolist() == [0, 0]  # the counters restart with the episode


def test_feedback_waits_for_its_arrival_and_credits_the_decisions_before_it():
    oracle = KeepawayOracle(3, 2, frequency=1.0, consistency=1.0, delay=0.3, seed=0)
    fk = _fused("linear", 0.5, trainer=oracle, credit=PreviousStep())
    model = fk.tamer.model
    obs = torch.zeros(1, 13)
    obs[0, 3] = 20.0  # nearest taker far away: the hand-coded policy holds
    tiles = model.tiles(torch.tensor([[0.0, 0.0]]))[:, 0]
    fk.decided(torch.tensor([0]), torch.tensor([1]), torch.tensor([0]), tiles, obs, torch.tensor([2.0]))
    assert fk.pending_time[0].min().item() == pytest.approx(2.3)
    fk.deliver(torch.tensor([2.2]))
    assert model.weight.abs().sum() == 0  # not yet
    fk.deliver(torch.tensor([2.4]))
    assert model(torch.tensor([0]), tiles).item() == pytest.approx(1.0, abs=1e-6)  # alpha 1, all credit
    assert fk.feedback.tolist() == [1] and fk.positive.tolist() == [1]
    assert torch.isinf(fk.pending_time).all()


def test_a_full_queue_delivers_its_oldest_event_early():
    oracle = KeepawayOracle(3, 2, frequency=1.0, consistency=1.0, delay=10.0, seed=0)
    model = TileCoding([1.0, 1.0], num_actions=3, learners=1, tilings=4, size=2**12)
    fk = FusedKeepers(
        "linear",
        ConstantWeight([0.5]),
        KeeperTamer(model, 1),
        oracle,
        3,
        torch.zeros(3, dtype=torch.int64),
        queue=2,
    )
    tiles = model.tiles(torch.tensor([[0.0, 0.0]]))[:, 0]
    for t in range(3):
        fk.decided(
            torch.tensor([0]),
            torch.tensor([0]),
            torch.tensor([0]),
            tiles,
            torch.zeros(1, 13),
            torch.tensor([float(t)]),
        )
    assert fk.early == 1 and fk.feedback.tolist() == [1]
    assert sorted(fk.pending_time[0].tolist()) == [11.0, 12.0]


def test_reward_shaping_adds_w_times_h_of_the_previous_decision():
    fk = _fused("reward_shaping", 2.0)
    _choose(fk, [1.0, 0.0, 0.0], [0.25, -1.0, 0.0])
    fk.decided(
        torch.tensor([0]),
        torch.tensor([1]),
        torch.tensor([0]),
        torch.zeros(1, 8, dtype=torch.int64),
        torch.zeros(1, 13),
        torch.tensor([0.0]),
    )
    assert fk.shaping(torch.tensor([1, 0])).tolist() == pytest.approx(
        [0.5, 0.0]
    )  # keeper 1's row; keeper 0: none
    fk.end_episodes(torch.tensor([0]), torch.tensor([3.0]))
    assert fk.shaping(torch.tensor([1])).tolist() == [0.0]


def test_oracle_timing_options():
    obs = torch.rand(256, 13, generator=torch.Generator().manual_seed(1)) * 10
    bad = torch.full((256,), 2)
    everyone = torch.ones(256, dtype=torch.bool)
    away = KeepawayOracle(3, 2, frequency=1.0, absence=1.0)
    away.new_episodes(everyone)
    assert not away.give(obs, bad, everyone, torch.zeros(256))[0].any()
    kind = KeepawayOracle(3, 2, frequency=1.0, consistency=1.0, positive_bias=1.0)
    assert bool((kind.give(obs, bad, everyone, torch.zeros(256))[0] >= 0).all())
    tired = KeepawayOracle(3, 2, frequency=1.0, fatigue_tau=10.0, seed=3)
    early = (tired.give(obs, bad, everyone, torch.zeros(256))[0] != 0).float().mean()
    late = (tired.give(obs, bad, everyone, torch.full((256,), 30.0))[0] != 0).float().mean()
    assert early > 0.9 and late < 0.15  # exp(-3) = 0.05
    follows_hold = KeepawayOracle(
        3, 2, frequency=1.0, consistency=1.0, reference=lambda o, k: torch.zeros_like(k)
    )
    values, _ = follows_hold.give(obs, torch.zeros(256, dtype=torch.int64), everyone, torch.zeros(256))
    assert bool((values == 1).all())


def _tiny_run(scheme: str, seed: int = 0, cycles: int = 200) -> tuple[FusedKeepers, KeepawayRecords]:
    config = KeepawayConfig(decision_period_cycles=5)
    agent = make_sarsa_keepers(config, 2, size=2**12, seed=seed)
    model = TileCoding(agent.coder.widths.tolist(), 3, learners=2, tilings=32, size=2**12)
    oracle = KeepawayOracle(3, 2, frequency=0.5, consistency=0.9, seed=seed)
    human = FusedKeepers(
        scheme, TrustWeight.from_initial(0.5, 2), KeeperTamer(model, 2), oracle, 3, torch.arange(6) // 3
    )
    records = KeepawayRecords(2, 3)
    run_sarsa_keepers(
        KeepawayEnv(2, config, seed=seed, sync="any"), agent, records, cycles=cycles, human=human
    )
    return human, records


def test_a_taught_run_learns_h_and_is_deterministic():
    one, rec = _tiny_run("linear")
    two, again = _tiny_run("linear")
    assert int(one.feedback.sum()) > 10 and one.tamer.model.weight.abs().sum() > 0
    assert torch.equal(one.tamer.model.weight, two.tamer.model.weight)
    assert torch.equal(rec.table, again.table)
    assert one.schedule.value().tolist() != [0.5, 0.5]  # eq. 4.4 ran at the episodes' ends
    human_only, _ = _tiny_run("human_only", cycles=60)
    assert not human_only.explores and human_only.tamer.model.weight.abs().sum() > 0


def test_config_checks_and_implied_choices():
    check_keepaway_feedback(_cfg())
    assert keepaway_config(_cfg()).decision_period_cycles == 5  # the thesis's 500 ms when a trainer watches
    assert keepaway_config(_cfg("trainer=none", "fusion=none")).decision_period_cycles == 1
    assert keepaway_config(_cfg("domain.decision_period_cycles=2")).decision_period_cycles == 2
    for overrides, message in [
        (["trainer=none"], "choose trainer=oracle"),
        (["agent.fields_per_learner=2"], "one trainer watches one field"),
        (["trainer=value_proxy"], "not available for keepaway"),
        (["trainer.timing.tail_lines=5"], "Tetris option"),
        (["human.model=crowd"], "human.model='crowd' is invalid"),
        (["fusion.weight=-1"], "fusion.weight=-1"),
    ]:
        with pytest.raises(ConfigError, match=message):
            check_keepaway_feedback(_cfg(*overrides))
    assert implied_overrides(["domain=keepaway", "fusion=linear"]) == [
        "agent=sarsa",
        "human=tile_coded",
        "trainer=oracle",
    ]
    assert implied_overrides(["domain=keepaway", "agent=sarsa", "human=tile_coded"]) == []
    assert implied_overrides(["fusion=exponential", "trainer=replay"]) == []
    assert implied_overrides(["fusion=none,linear", "-m"]) == []
    assert implied_overrides(["resume=outputs/x", "domain=keepaway"]) == []


def test_train_with_a_trainer_logs_feedback_and_resumes(tmp_path):
    small = ["agent.learners=2", "agent.table_bits=12", "agent.log_minutes=0.1", "agent.log_episodes=2"]
    final = train_sarsa(_cfg(*small, "agent.hours=0.006"), tmp_path)
    assert final["feedback_events"] > 0 and "fusion/weight_mean" in final
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert len(events) >= final["feedback_events"] and events[0].source == "simulated:keepaway_oracle"
    lines = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert all("feedback/credited_share" in line for line in lines)
    ckpt = load_checkpoint(tmp_path, domain="keepaway", agent="sarsa")
    assert ckpt["state"]["human"]["human_weight"].abs().sum() > 0
    train_sarsa(_cfg(*small, "agent.hours=0.012"), tmp_path, checkpoint=ckpt)
    again = load_checkpoint(tmp_path)["state"]["human"]
    assert int(again["feedback"].sum()) > int(ckpt["state"]["human"]["feedback"].sum())


def test_replay_gives_each_fields_events_when_its_clock_passes_them(tmp_path):
    events = [
        FeedbackEvent(time=2.0, value=1.0, source="simulated:keepaway_oracle", session="s/board1"),
        FeedbackEvent(time=1.0, value=-1.0, source="simulated:keepaway_oracle", session="s/board1"),
        FeedbackEvent(time=1.5, value=1.0, source="human:browser", session="person"),  # one field: to all
    ]
    log = FeedbackLog(tmp_path / "feedback.jsonl", session="new")
    replay = KeepawayReplay(events, fields=2, log=log)
    values, times = replay.poll(torch.tensor([1.6, 1.2]))
    assert values.tolist() == [1.0, -1.0] and times.tolist() == [1.5, 1.0]
    assert replay.poll(torch.tensor([1.6, 1.2]))[0].tolist() == [0.0, 0.0]  # nothing else due yet
    assert replay.poll(torch.tensor([9.0, 9.0]))[0].tolist() == [0.0, 1.0]  # field 1: 1.5 s
    saved = replay.state_dict()
    assert replay.poll(torch.tensor([9.0, 9.0]))[0].tolist() == [0.0, 1.0]  # field 1: 2.0 s
    assert replay.poll(torch.tensor([99.0, 99.0]))[0].tolist() == [0.0, 0.0]  # all given
    again = KeepawayReplay(events, fields=2)
    again.load_state_dict(saved)
    assert again.poll(torch.tensor([9.0, 9.0]))[1].tolist() == [0.0, 2.0]
    log.close()
    logged = load_feedback_log(tmp_path / "feedback.jsonl")
    assert len(logged) == 4 and {e.source for e in logged} == {"replay"}  # field 0: 1; field 1: 3
    assert [e.session for e in logged[:2]] == ["new/board0", "new/board1"]


def test_a_recorded_run_replays_into_a_new_one_and_the_oracle_can_follow_a_checkpoint(tmp_path):
    small = ["agent.learners=2", "agent.table_bits=12", "agent.log_minutes=0.1", "agent.hours=0.004"]
    first = tmp_path / "first"
    first.mkdir()
    recorded = train_sarsa(_cfg(*small), first)["feedback_events"]
    second = tmp_path / "second"
    second.mkdir()
    final = train_sarsa(_cfg(*small, "trainer=replay", f"trainer.log={first / 'feedback.jsonl'}"), second)
    replayed = load_feedback_log(second / "feedback.jsonl")
    assert 0 < final["feedback_events"] <= recorded and len(replayed) == final["feedback_events"]
    assert {e.source for e in replayed} == {"replay"}
    assert load_checkpoint(second)["state"]["human"]["human_weight"].abs().sum() > 0

    judged = tmp_path / "judged"
    judged.mkdir()
    final = train_sarsa(_cfg(*small, f"trainer.reference={first}"), judged)
    assert final["feedback_events"] > 0
    with pytest.raises(ConfigError, match=r"trainer\.reference='nowhere' is invalid"):
        check_keepaway_feedback(_cfg("trainer.reference=nowhere"))
    with pytest.raises(ConfigError, match=r"needs trainer\.log"):
        check_keepaway_feedback(_cfg("trainer=replay"))
