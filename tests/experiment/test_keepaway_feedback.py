"""Keepers taught by a (simulated) trainer: the fusion of Q and H^ through the one component, the feedback
channel on each field's clock, the reward shaping transform on the env, trust from hold time, and the
keepaway learner with a trainer through train.py's loop."""

from __future__ import annotations

import json

import pytest
import torch
from omegaconf import open_dict
from tensordict import TensorDict
from torchrl.envs import TransformedEnv

from hfrl_torch import keys
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawayEnv
from hfrl_torch.experiment.factories import make_fusion, make_keepaway_config
from hfrl_torch.experiment.learners.keepaway_sarsa import SarsaKeepers
from hfrl_torch.feedback.channel import FeedbackChannel
from hfrl_torch.feedback.credit import PreviousStep
from hfrl_torch.feedback.events import FeedbackEvent
from hfrl_torch.feedback.log import FeedbackLog, load_feedback_log
from hfrl_torch.fusion import ConstantWeight, FeedbackFusion, Fusion, FusionModule, TrustWeight
from hfrl_torch.models.tile_coding import TileCoding
from hfrl_torch.trainers.keepaway_oracle import KeepawayOracle
from hfrl_torch.trainers.keepaway_replay import KeepawayReplay

TAUGHT = ["domain=keepaway", "trainer=oracle", "fusion=linear"]


def _cfg(compose_train, *overrides: str):
    return compose_train(*TAUGHT, *overrides)


def _choose(scheme: str, weight: float, q, h, mask=(True, True, True), scaling: str = "decision") -> int:
    """The deciding keeper's argmax of the fused values (Sarsa's greedy choice) for one decision."""
    fusion = Fusion.from_option(scheme, ConstantWeight([weight]), scaling=scaling)
    decisions = TensorDict(
        {
            keys.ENV_VALUES: torch.tensor([q], dtype=torch.float64),
            keys.HUMAN_VALUES: torch.tensor([h], dtype=torch.float64),
            keys.ACTION_MASK: torch.tensor([mask]),
            keys.LEARNER: torch.tensor([0]),
        },
        batch_size=[1],
    )
    values = FusionModule(fusion)(decisions)[keys.FUSED_VALUES]
    return int(values.masked_fill(~torch.tensor([mask]), -torch.inf).argmax())


def test_fusion_rules_choose_as_the_thesis_writes_them():
    q, h = [10.0, 8.0, 0.0], [-1.0, 1.0, 0.0]  # Q prefers hold, H^ the first pass
    assert _choose("none", 0.5, q, h) == 0
    assert _choose("human_only", 0.5, q, h) == 1
    # rescaled: Q -> [1, 0.8, 0], H^ -> [0, 1, 0.5]; linear 1 + w*0 vs 0.8 + w*1
    assert _choose("linear", 0.1, q, h) == 0
    assert _choose("linear", 0.5, q, h) == 1
    # exponential: R (1 + H^w): 1 * 1 vs 0.8 * 2 for any w > 0
    assert _choose("exponential", 0.5, q, h) == 1
    assert _choose("reward_shaping", 5.0, q, h) == 0  # shaping acts on the reward, not the choice
    assert _choose("control_sharing", 1.0, q, h) == 1
    assert _choose("control_sharing", 0.0, q, h) == 0
    assert _choose("linear", 100.0, q, h, mask=(True, False, False)) == 0  # only hold available
    # keepaway's default scale: H^ times Q's running spread, 0.99 * 1 + 0.01 * 10 = 1.09 after this decision
    assert _choose("linear", 1.0, q, h, scaling="spread") == 1  # 10 - 1.09 < 8 + 1.09
    assert _choose("linear", 1.0, [10.0, 7.0, 0.0], h, scaling="spread") == 0  # 10 - 1.09 > 7 + 1.09


def test_trust_follows_eq_4_4_on_hold_time_per_learner():
    fusion = Fusion.from_option("linear", TrustWeight.from_initial(0.5, learners=2))
    fusion.matches.add(torch.tensor([0]), torch.tensor([1]), torch.tensor([4]))
    fusion.end_episode(torch.tensor([True, True]), torch.tensor([6.0, 9.0]))
    # first episode: l1 = l2 -> (0.5 + 0.25) / 2; field 1 compared nothing: trust kept
    assert fusion.weight().tolist() == pytest.approx([0.375, 0.5])
    fusion.matches.add(torch.tensor([0]), torch.tensor([2]), torch.tensor([2]))
    fusion.end_episode(torch.tensor([True, False]), torch.tensor([3.0, 0.0]))
    assert fusion.weight().tolist() == pytest.approx([(6 * 0.375 + 3 * 1.0) / 9, 0.5])
    assert fusion.matches.compared.tolist() == [0, 0]  # the counters restart with the episode


def test_feedback_waits_for_its_arrival_and_credits_the_decisions_before_it():
    oracle = KeepawayOracle(3, 2, frequency=1.0, consistency=1.0, delay=0.3, seed=0)
    model = TileCoding([1.0, 1.0], num_actions=3, learners=1, tilings=4, size=2**12)
    tamer = KeeperTamer(model, 1, alpha=1.0, credit=PreviousStep())
    channel = FeedbackChannel(1)
    obs = torch.zeros(1, 13)
    obs[0, 3] = 20.0  # nearest taker far away: the hand-coded policy holds
    tiles = model.tiles(torch.tensor([[0.0, 0.0]]))[:, 0]
    tamer.record(torch.tensor([True]), torch.tensor([0]), tiles, torch.tensor([2.0]))
    values, times = oracle.give(
        obs, torch.tensor([0]), torch.tensor([True]), torch.tensor([2.0]), torch.tensor([1])
    )
    channel.put(values, times, oracle.source)
    assert times.tolist() == pytest.approx([2.3]) and channel.pending == 1
    early = channel.deliver(torch.tensor([2.2]))
    assert not early[keys.FEEDBACK_MASK].any() and tamer.learn(early) == 0  # not yet
    due = channel.deliver(torch.tensor([2.4]))
    assert due[keys.FEEDBACK].tolist() == [[1.0, 0.0, 0.0, 0.0]] and due[keys.FEEDBACK_TIME][
        0, 0
    ] == pytest.approx(2.3)
    assert tamer.learn(due) == 1
    assert model(torch.tensor([0]), tiles).item() == pytest.approx(1.0, abs=1e-6)  # alpha 1, all credit
    assert channel.pending == 0


def test_reward_shaping_on_the_env_adds_w_times_h_of_each_keepers_previous_decision():
    """Each keeper's SMDP reward, and at the end every keeper's last one, plus w H^ of that keeper's own
    previous decision; checked against the same env without the transform, step by step."""
    config = KeepawayConfig(decision_period_cycles=5, kernels="cycle", **TASKS["exact"])
    raw = KeepawayEnv(2, config, seed=3, sync="any")
    fusion = Fusion.from_option("reward_shaping", ConstantWeight([2.0, 2.0]))
    shaped = TransformedEnv(
        KeepawayEnv(2, config, seed=3, sync="any"),
        FeedbackFusion(
            fusion,
            agent_key=keys.KEEPER,
            agents=3,
            deciding_key=keys.DECIDING,
            agent_rewards_key=keys.EPISODE_END_REWARDS,
        ),
    )
    td, plain = shaped.reset(), raw.reset()
    last_h: dict[tuple[int, int], float] = {}
    decisions = ends = 0
    gen = torch.Generator().manual_seed(0)
    for _ in range(250):
        deciding, keeper = td[keys.DECIDING].clone(), td[keys.KEEPER].clone()
        estimate = torch.where(deciding, torch.rand(2, generator=gen) - 0.5, 0.0).unsqueeze(-1)
        action = torch.randint(0, 3, (2,), generator=gen)
        td.set(keys.HUMAN_REWARD_ESTIMATE, estimate).set(keys.ACTION, action)
        td, td_next = shaped.step_and_maybe_reset(td)
        plain, plain_next = raw.step_and_maybe_reset(plain.set(keys.ACTION, action))
        after, env_after = td["next"], plain["next"]
        assert torch.equal(after[keys.ENV_REWARD], env_after[keys.REWARD])
        for f in range(2):
            if bool(deciding[f]):
                last_h[(f, int(keeper[f]))] = float(estimate[f, 0])
            if bool(after[keys.DONE][f]):
                for k in range(3):
                    want = float(env_after[keys.EPISODE_END_REWARDS][f, k]) + 2.0 * last_h.pop((f, k), 0.0)
                    assert float(after[keys.EPISODE_END_REWARDS][f, k]) == pytest.approx(want, abs=1e-5)
                ends += 1
            elif bool(after[keys.DECIDING][f]):
                k = int(after[keys.KEEPER][f])
                want = float(env_after[keys.REWARD][f]) + 2.0 * last_h.get((f, k), 0.0)
                assert float(after[keys.REWARD][f]) == pytest.approx(want, abs=1e-5)
                decisions += 1
            else:  # nobody decides: no SMDP reward to shape
                assert float(after[keys.REWARD][f]) == float(env_after[keys.REWARD][f]) == 0.0
        td, plain = td_next, plain_next
    assert decisions > 20 and ends >= 2


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


def _tiny(compose_train, run_learner, tmp_path, scheme: str, seed: int = 0, hours: float = 0.011):
    over = [
        "agent.learners=2",
        "agent.table_bits=12",
        f"fusion={scheme}",
        f"seed={seed}",
        f"agent.hours={hours}",
    ]
    over += ["agent.log_minutes=0.1"]
    return run_learner(tmp_path, *TAUGHT, *over)


def test_a_taught_run_learns_h_and_is_deterministic(tmp_path, compose_train, run_learner):
    one, _ = _tiny(compose_train, run_learner, tmp_path / "a", "linear")
    two, _ = _tiny(compose_train, run_learner, tmp_path / "b", "linear")
    assert int(one.feedback.sum()) > 10 and one.tamer.model.weight.abs().sum() > 0
    assert torch.equal(one.tamer.model.weight, two.tamer.model.weight)
    assert torch.equal(one.records.table, two.records.table)
    assert one.fusion.weight().tolist() != [0.5, 0.5]  # eq. 4.4 ran at the episodes' ends
    human_only, _ = _tiny(compose_train, run_learner, tmp_path / "c", "human_only", hours=0.004)
    assert not human_only.fusion.explores and human_only.tamer.model.weight.abs().sum() > 0


def test_keepers_whose_weight_a_bandit_chooses_act_greedily_on_the_fused_values(compose_train):
    """agent.greedy_with_bandit: under the adaptive weight (a bandit over weights) the keepers choose
    greedily, the bandit's weights being the exploration; under the thesis's trust factor, a fixed weight, or
    when H^ only shapes the reward, they explore as the reference keepers do."""

    def explores(*overrides: str) -> bool:
        return make_fusion(_cfg(compose_train, *overrides), SarsaKeepers, 2).explores

    assert not explores()  # fusion=linear, weight=adaptive: the default
    assert not explores("fusion=exponential")
    assert explores("agent.greedy_with_bandit=false")
    assert explores("fusion.weight=trust") and explores("fusion.weight=4.0")
    assert explores("fusion=reward_shaping", "fusion.weight=adaptive")  # the choice is on Q alone
    assert not explores("fusion=human_only")  # TAMER's choice is greedy whatever the flag
    with pytest.raises(ConfigError, match=r"agent\.greedy_with_bandit"):
        _cfg(compose_train, "agent.greedy_with_bandit=sometimes")
    saved = _cfg(compose_train)  # a run saved before the option explores, as it did then
    with open_dict(saved):
        del saved.agent["greedy_with_bandit"]
    assert make_fusion(saved, SarsaKeepers, 2).explores


def test_config_checks_and_the_choices_the_config_implies(compose_train):
    cfg = _cfg(compose_train)
    assert cfg.agent.name == "sarsa" and cfg.human.name == "tile_coded"  # domain=keepaway brings them
    assert make_keepaway_config(cfg).decision_period_cycles == 5  # the thesis's 500 ms when a trainer watches
    assert (
        make_keepaway_config(_cfg(compose_train, "trainer=none", "fusion=none")).decision_period_cycles == 1
    )
    assert (
        make_keepaway_config(_cfg(compose_train, "domain.decision_period_cycles=2")).decision_period_cycles
        == 2
    )
    implied = compose_train("domain=keepaway", "fusion=exponential")  # trainer=auto: the simulated oracle
    assert implied.trainer.name == "oracle" and implied.domain.decision_period_cycles == 5
    assert compose_train("domain=keepaway", "trainer=interactive").agent.learners == 1  # one person, one team
    for overrides, message in [
        (["trainer=none"], "choose trainer=oracle"),
        (["agent.fields_per_learner=2"], "one trainer watches one field"),
        (["trainer=value_proxy"], "not available for keepaway"),
        (["trainer.timing.tail_lines=5"], "Tetris option"),
        (["human.model=crowd"], "human.model='crowd' is invalid"),
        (["fusion.weight=-1"], "fusion.weight=-1"),
        (["trainer=interactive", "agent.learners=3"], "one person teaches one team"),
    ]:
        with pytest.raises(ConfigError, match=message):
            _cfg(compose_train, *overrides)


def test_train_with_a_trainer_logs_feedback_and_resumes(tmp_path, run_learner):
    small = ["agent.learners=2", "agent.table_bits=12", "agent.log_minutes=0.1", "agent.log_episodes=2"]
    _, final = run_learner(tmp_path, *TAUGHT, *small, "agent.hours=0.006")
    assert final["feedback_events"] > 0 and "fusion/weight_mean" in final
    events = load_feedback_log(tmp_path / "feedback.jsonl")
    assert len(events) >= final["feedback_events"] and events[0].source == "simulated:keepaway_oracle"
    lines = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert all("feedback/credited_share" in line for line in lines)
    ckpt = load_checkpoint(tmp_path, domain="keepaway", agent="sarsa")
    assert ckpt["state"]["human"]["human_weight"].abs().sum() > 0
    run_learner(tmp_path, *TAUGHT, *small, "agent.hours=0.012", checkpoint=ckpt)
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


def test_a_recorded_run_replays_into_a_new_one_and_the_oracle_can_follow_a_checkpoint(
    tmp_path, compose_train, run_learner
):
    small = ["agent.learners=2", "agent.table_bits=12", "agent.log_minutes=0.1", "agent.hours=0.004"]
    first = tmp_path / "first"
    recorded = run_learner(first, *TAUGHT, *small)[1]["feedback_events"]
    second = tmp_path / "second"
    _, final = run_learner(
        second, *TAUGHT, *small, "trainer=replay", f"trainer.log={first / 'feedback.jsonl'}"
    )
    replayed = load_feedback_log(second / "feedback.jsonl")
    assert 0 < final["feedback_events"] <= recorded and len(replayed) == final["feedback_events"]
    assert {e.source for e in replayed} == {"replay"}
    assert load_checkpoint(second)["state"]["human"]["human_weight"].abs().sum() > 0

    _, final = run_learner(tmp_path / "judged", *TAUGHT, *small, f"trainer.reference={first}")
    assert final["feedback_events"] > 0
    with pytest.raises(ConfigError, match=r"trainer\.reference='nowhere' is invalid"):
        _cfg(compose_train, "trainer.reference=nowhere")
    with pytest.raises(ConfigError, match=r"needs trainer\.log"):
        _cfg(compose_train, "trainer=replay")
