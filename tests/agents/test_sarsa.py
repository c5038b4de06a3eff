"""SMDP Sarsa(lambda) keepers: the three routines of the thesis's Figure 5.4 against hand-computed weights,
replacing traces, epsilon-greedy ties, the learner batch, per-keeper SMDP rewards in keepaway, a short
learning run against the random policy, and the keepaway learner with its checkpoint and resume."""

from __future__ import annotations

import json

import pytest
import torch

from hfrl_torch.agents.sarsa import SarsaLambda, SarsaLambdaNumba, trace_capacity
from hfrl_torch.agents.sarsa import sarsa_keepers as make_sarsa_keepers
from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.envs.keepaway import TASKS, KeepawayConfig, KeepawayEnv, play_benchmark_policy
from hfrl_torch.experiment.checks import check_sarsa
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.models.tile_coding import TileCoding, keepaway_tile_widths

torch.set_num_threads(1)


# the torch learner and its compiled twin pass the same hand-computed scripts (float64 weights: exact)
LEARNERS = pytest.mark.parametrize("learner", [SarsaLambda, SarsaLambdaNumba], ids=["torch", "numba"])


def _tiny_agent(lambda_: float, learners: int = 1, learner: type = SarsaLambda, **kwargs) -> SarsaLambda:
    """One variable of width 1, two tilings, two actions: N = 2 active tiles, so alpha / N = 0.25."""
    coder = TileCoding([1.0], num_actions=2, learners=learners, tilings=2, size=2**10, dtype=torch.float64)
    return learner(coder, alpha=0.5, epsilon=0.0, lambda_=lambda_, **kwargs)


def _trace(agent: SarsaLambda, learner: int, tile: int) -> float:
    hit = (agent.trace_index[learner] == tile) & (agent.trace_value[learner] > 0)
    return float(agent.trace_value[learner][hit].sum())


ONE = torch.tensor([0])
BOTH = torch.ones(1, 2, dtype=torch.bool)


@LEARNERS
@pytest.mark.parametrize("lambda_", [0.0, 0.5])
def test_three_routines_on_a_scripted_episode(lambda_, learner):
    agent = _tiny_agent(lambda_, learner=learner)
    w = agent.coder.weight[0]
    s0, s1 = torch.tensor([[0.25]]), torch.tensor([[1.75]])  # tiles (0, -1) and (1, 1) of the two tilings
    tiles = torch.cat((agent.coder.tiles(s0), agent.coder.tiles(s1)))  # [2 states, 2 actions, 2 tiles]
    assert tiles.unique().numel() == 8  # no hash collision in this script

    # RLstartEpisode: Q = 0 everywhere, random tie-break; no learning, e = 1 on F_a0(s0)
    a0 = int(agent.start_episode(ONE, s0, BOTH))
    f0 = tiles[0, a0]
    assert w.abs().sum() == 0 and float(agent.q_last[0]) == 0.0
    assert [_trace(agent, 0, int(i)) for i in f0] == [1.0, 1.0]

    # RLstep, r = 3: delta = 3 - Q(s0, a0) + Q(s1, a1) = 3; each trace-1 weight += alpha / N * 3 = 0.75
    a1 = int(agent.step(ONE, torch.tensor([3.0]), s1, BOTH))
    f1 = tiles[1, a1]
    assert w[f0].tolist() == [0.75, 0.75]
    assert float(agent.q_last[0]) == 0.0  # Q(s1, a1) recomputed after the update (line 18)

    # RLstep, r = 2, back in s0: greedy a0 (Q = 1.5 against 0); delta = 2 - 0 + 1.5 = 3.5
    a2 = int(agent.step(ONE, torch.tensor([2.0]), s0, BOTH))
    assert a2 == a0
    if lambda_ == 0.0:  # only F_a1(s1) has a trace (1)
        assert w[f0].tolist() == [0.75, 0.75]
        assert w[f1].tolist() == [0.875, 0.875]
        assert float(agent.q_last[0]) == 1.5
    else:  # F_a0(s0) still has 0.5, F_a1(s1) has 1
        assert w[f0].tolist() == [0.75 + 0.25 * 3.5 * 0.5] * 2
        assert w[f1].tolist() == [0.875, 0.875]
        assert float(agent.q_last[0]) == 2 * 1.1875
        # replacing traces: F_a0(s0) is set back to 1 (not 1 + 0.25); F_a1(s1) decayed to 0.5
        assert [_trace(agent, 0, int(i)) for i in f0] == [1.0, 1.0]
        assert [_trace(agent, 0, int(i)) for i in f1] == [0.5, 0.5]

    # RLendEpisode, r = 4: delta = 4 - Q_LastAction, the terminal state being worth 0
    agent.end_episode(ONE, torch.tensor([4.0]))
    if lambda_ == 0.0:  # delta = 4 - 1.5 = 2.5 on F_a0(s0) only
        assert w[f0].tolist() == [0.75 + 0.25 * 2.5] * 2
        assert w[f1].tolist() == [0.875, 0.875]
    else:  # delta = 4 - 2.375 = 1.625, traces 1 and 0.5
        assert w[f0].tolist() == [1.1875 + 0.25 * 1.625] * 2
        assert w[f1].tolist() == [0.875 + 0.25 * 1.625 * 0.5] * 2
    assert int(agent.last_action[0]) == -1
    assert int((w != 0).sum()) == 4  # nothing else moved
    with pytest.raises(ValueError):
        agent.step(ONE, torch.tensor([1.0]), s0, BOTH)  # no pending action after the end


@LEARNERS
@pytest.mark.parametrize("available", [True, False])
def test_traces_of_other_available_actions_are_cleared(available, learner):
    agent = _tiny_agent(lambda_=1.0, learner=learner)
    s0, s1 = torch.tensor([[0.25]]), torch.tensor([[0.75]])  # share the tile of tiling 0 (coordinate 0)
    f_s0, f_s1 = agent.coder.tiles(s0)[0], agent.coder.tiles(s1)[0]
    shared, kept = int(f_s0[1, 0]), int(f_s0[1, 1])
    assert shared == int(f_s1[1, 0])
    w = agent.coder.weight[0]
    w[f_s0[1]] = 1.0  # Q(s0, 1) = 2 > Q(s0, 0) = 0
    w[f_s1[0, 1]] = 5.0  # Q(s1, 0) = 5 > Q(s1, 1) = 1
    assert int(agent.start_episode(ONE, s0, BOTH)) == 1
    mask = torch.tensor([[True, available]])
    assert int(agent.step(ONE, torch.tensor([1.0]), s1, mask)) == 0
    assert w[f_s0[1]].tolist() == [2.0, 2.0]  # delta = 1 - 2 + 5 = 4, alpha / N = 0.25, trace 1
    assert float(agent.q_last[0]) == 5.0
    # action 1's tile shared by s0 and s1 loses its trace only if action 1 was available in s1
    assert _trace(agent, 0, shared) == (0.0 if available else 1.0)
    assert _trace(agent, 0, kept) == 1.0  # lambda = 1: no decay
    assert [_trace(agent, 0, int(i)) for i in f_s1[0]] == [1.0, 1.0]


def test_epsilon_greedy_with_random_ties_and_mask():
    coder = TileCoding([1.0], num_actions=3, learners=1, tilings=1, size=8)
    agent = SarsaLambda(coder, epsilon=0.0, seed=3)
    zeros = torch.zeros(6000, 3)
    counts = torch.bincount(agent.select(zeros, torch.ones(6000, 3, dtype=torch.bool)), minlength=3)
    assert counts.min() > 1800  # ties broken uniformly
    masked = agent.select(zeros, torch.tensor([[True, False, True]]).expand(6000, 3))
    assert not bool((masked == 1).any()) and bool((masked == 0).any()) and bool((masked == 2).any())
    q = torch.tensor([[0.0, 1.0, -1.0]]).expand(10000, 3)
    assert bool((agent.select(q, torch.ones(10000, 3, dtype=torch.bool)) == 1).all())
    agent.epsilon = 0.01
    share = float((agent.select(q, torch.ones(10000, 3, dtype=torch.bool)) != 1).float().mean())
    assert 0.002 < share < 0.015  # epsilon * 2/3
    agent.epsilon = 1.0
    uniform = agent.select(q, torch.tensor([[True, False, True]]).expand(10000, 3))
    assert set(uniform.tolist()) == {0, 2}


@LEARNERS
def test_learner_batch_equals_separate_learners(learner):
    gen = torch.Generator().manual_seed(4)
    widths = keepaway_tile_widths()
    start = torch.rand(2, 2**10, generator=gen, dtype=torch.float64)  # no ties: deterministic choices
    obs = [torch.rand(2, 13, generator=gen) * 15 for _ in range(4)]
    rewards = [torch.tensor([3.0, 7.0]), torch.tensor([1.0, 2.0]), torch.tensor([5.0, 1.0])]
    mask = torch.ones(2, 3, dtype=torch.bool)

    def agent(learners: int) -> SarsaLambda:
        coder = TileCoding(widths, 3, learners=learners, size=2**10, dtype=torch.float64)
        return learner(coder, epsilon=0.0, lambda_=0.7)

    both = agent(2)
    both.coder.weight.copy_(start)
    both.start_episode(torch.arange(2), obs[0], mask)
    for r, o in zip(rewards, obs[1:], strict=True):
        both.step(torch.arange(2), r, o, mask)
    both.end_episode(torch.arange(2), torch.tensor([2.0, 9.0]))
    for i in range(2):
        one = agent(1)
        one.coder.weight.copy_(start[i : i + 1])
        one.start_episode(ONE, obs[0][i : i + 1], mask[:1])
        for r, o in zip(rewards, obs[1:], strict=True):
            one.step(ONE, r[i : i + 1], o[i : i + 1], mask[:1])
        one.end_episode(ONE, torch.tensor([2.0, 9.0])[i : i + 1])
        assert torch.allclose(one.coder.weight[0], both.coder.weight[i], rtol=0, atol=1e-12)
    with pytest.raises(ValueError):
        both.decide(torch.tensor([1, 1]), obs[0], mask, torch.zeros(2))


def test_trace_capacity_and_bounded_traces():
    assert trace_capacity(416, 0.0, 0.01) == 416
    assert trace_capacity(416, 0.5, 0.01) == 416 * (1 + 6)  # 0.5^6 = 0.016 >= 0.01 > 0.5^7
    assert trace_capacity(416, 1.0, 0.01) == 100_000
    agent = make_sarsa_keepers(KeepawayConfig(), 1, lambda_=0.9, max_traces=1000, size=2**12)
    gen = torch.Generator().manual_seed(5)
    learners, mask = torch.tensor([0]), torch.ones(1, 3, dtype=torch.bool)
    agent.start_episode(learners, torch.rand(1, 13, generator=gen) * 20, mask)
    for _ in range(5):  # far-apart states: more traces than slots, the smallest are dropped first
        obs = torch.rand(1, 13, generator=gen) * 20
        action = agent.step(learners, torch.ones(1), obs, mask)
    values = agent.trace_value[0]
    assert agent.trace_index.shape == (3, 1000)
    chosen = agent.coder.tiles(obs)[0, int(action)].unique()  # (2^12 weights: some tiles collide)
    ones = agent.trace_index[0][values == 1.0]
    assert torch.equal(ones.sort().values, chosen)  # the last decision's tiles are all kept, at 1
    assert float(values[values < 1].max()) == pytest.approx(0.9)
    live = agent.trace_index[0][values > 0]
    assert live.unique().numel() == live.numel()  # one slot per tile


class RecordingSarsa(SarsaLambda):
    """Sarsa that also notes, for every call, what each keeper received and the env's episode clock."""

    def __init__(self, env: KeepawayEnv, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.env, self.events = env, []

    def decide(self, learners, obs, mask, reward, **kwargs):
        starting = self.last_action[learners] < 0
        clock = self.env.sim.state.episode_cycles.clone()
        self.events.append(("decide", learners.tolist(), starting.tolist(), reward.tolist(), clock.tolist()))
        return super().decide(learners, obs, mask, reward, **kwargs)

    def end_episode(self, learners, reward):
        pending = self.last_action[learners] >= 0
        self.events.append(("end", learners.tolist(), pending.tolist(), reward.tolist(), None))
        super().end_episode(learners, reward)


KEEPAWAY = ["domain=keepaway", "logger=none"]
EXACT = TASKS["exact"]  # the exact-state task, the env these tests put in the learner's place


@pytest.mark.parametrize("sync,per_learner", [("all", 1), ("any", 1), ("any", 3)])
def test_smdp_rewards_are_per_keeper(tmp_path, run_learner, sync, per_learner):
    teams, n = 3, 3
    fields = teams * per_learner

    def record_every_call(learner) -> None:
        """The learner's env in the ``sync`` mode under test, and Sarsa keepers that note every call."""
        learner.env = KeepawayEnv(fields, KeepawayConfig(**EXACT), seed=11, sync=sync)
        coder = TileCoding(keepaway_tile_widths(), 3, learners=teams * n, size=2**12)
        slots = torch.arange(fields * n)
        tables = (slots // n // per_learner) * n + slots % n  # each field's keepers: their team's tables
        learner.agent_sarsa = RecordingSarsa(learner.env, coder, epsilon=0.3, seed=11, tables=tables)

    over = [*KEEPAWAY, f"agent.learners={teams}", f"agent.fields_per_learner={per_learner}", "agent.hours=0"]
    learner, _ = run_learner(tmp_path, *over, f"agent.episodes={2 * per_learner}", prepare=record_every_call)
    agent, records = learner.agent_sarsa, learner.records

    durations = {f: [] for f in range(fields)}
    for row in records.table.tolist():
        durations[row[0]].append(row[3])
    episode = dict.fromkeys(range(fields), 0)
    last = {}  # learner -> cycle of its last decision in the current episode
    received = {}  # learner -> rewards received after its first decision
    first = {}
    checked = 0
    for kind, learners, flags, rewards, clock in agent.events:
        for learner, flag, reward in zip(learners, flags, rewards, strict=True):
            field = learner // n
            if kind == "decide":
                now = clock[field]
                if flag:  # RLstartEpisode: the keeper's first decision of the episode
                    assert learner not in last
                    first[learner], received[learner] = now, 0.0
                else:  # RLstep: cycles since this keeper's own last decision
                    assert reward == now - last[learner]
                    received[learner] += reward
                last[learner] = now
            else:
                duration = durations[field][episode[field]]
                assert flag == (learner in last)
                if flag:  # RLendEpisode: cycles since its last decision; all rewards add up to the rest
                    assert reward == duration - last[learner]
                    assert received[learner] + reward == duration - first[learner]
                    checked += 1
                    del last[learner]
                else:
                    assert reward == 0.0
                if learner % n == n - 1:
                    episode[field] += 1
    assert records.table.shape[0] >= teams * 2 * per_learner
    assert checked >= 1.5 * records.table.shape[0]  # most episodes involve at least two keepers
    decided = sum(len(e[1]) for e in agent.events if e[0] == "decide")
    assert int(records.table[:, 5:].sum() + records.decisions.sum()) == decided  # per-keeper counts


def test_short_learning_run_beats_the_random_policy(tmp_path, run_learner):
    # 500 ms decisions (the thesis's setting) and one weight table shared by the keepers of all 32
    # fields, so that about half a simulated hour of experience, half a minute of CPU, reaches one learner.
    random = play_benchmark_policy(
        "random", 400, batch=200, seed=7, progress=False, decision_period_cycles=5, kernels="cycle", **EXACT
    )
    fields = 32

    def one_shared_table(learner) -> None:
        """The fields in lock-step (``sync="all"``) and one weight table for the keepers of every field."""
        learner.env = KeepawayEnv(
            fields, KeepawayConfig(decision_period_cycles=5, kernels="cycle", **EXACT), seed=7
        )
        coder = TileCoding(keepaway_tile_widths(), 3, learners=1, size=2**18)
        learner.agent_sarsa = SarsaLambda(coder, seed=7, tables=torch.zeros(fields * 3, dtype=torch.int64))

    over = [
        *KEEPAWAY,
        "agent.learners=1",
        f"agent.fields_per_learner={fields}",
        "domain.decision_period_cycles=5",
    ]
    over += [f"agent.hours={600 * fields / 36000}", "seed=7", "agent.log_minutes=60"]
    learner, _ = run_learner(tmp_path, *over, prepare=one_shared_table)
    table = learner.records.table.double()
    table[:, 2] = table[:, 2] / fields  # the field's own clock (the learner's is the sum of its 32 fields')
    late = table[table[:, 2] >= 400, 3] / 10.0  # episodes that ended in the last third
    assert late.numel() >= 50  # 97 at seed 7
    # 7.9 s vs the random policy's upper 95 % bound of 6.3 s at seed 7 (whole compiled cycles: 3 s of CPU)
    print(f"late mean {float(late.mean()):.2f} s vs random's ci95_high {random['ci95_high']:.2f} s")
    assert float(late.mean()) > random["ci95_high"], (float(late.mean()), random["mean_s"])


def _cfg(*overrides: str):
    return compose_config("train", "domain=keepaway", "agent=sarsa", "logger=none", *overrides)


def _train(run_dir, run_learner, *overrides: str, checkpoint=None):
    return run_learner(run_dir, *KEEPAWAY, *overrides, checkpoint=checkpoint)[1]


def test_defaults_are_valid_and_bad_values_fail():
    check_sarsa(_cfg())
    for override, message in [
        ("agent.hours=0", "leave no budget"),
        ("agent.epsilon=1.5", "agent.epsilon=1.5 is invalid"),
        ("agent.lambda=-0.1", "agent.lambda=-0.1 is invalid"),
        ("agent.table_bits=31", "agent.table_bits=31 is invalid"),
        ("agent.max_traces=10", "agent.max_traces=10 is invalid"),
        ("agent.learners=5000", "GiB"),
        ("agent.fields_per_learner=0", "agent.fields_per_learner=0 is invalid"),
        ("agent.fields_per_learner=5000 agent.lambda=0.9", "GiB"),  # trace slots per field and keeper
        ("domain.takers=1", "domain.takers=1 is invalid"),
    ]:
        with pytest.raises(ConfigError, match=message):
            check_sarsa(_cfg(*override.split()))


def test_train_writes_curves_and_checkpoint_and_resumes(tmp_path, run_learner):
    small = ["agent.learners=2", "agent.table_bits=12", "agent.log_minutes=0.05", "agent.log_episodes=1"]
    final = _train(tmp_path, run_learner, *small, "agent.hours=0.003", "agent.checkpoint_minutes=0.1")
    lines = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert {"hours", "episodes"} <= {line["axis"] for line in lines}
    assert final["episode_s_mean"] > 0 and 1 <= final["learners"] <= 2
    assert max(line["learners"] for line in lines) == 2  # windows count the learners with episodes in them
    ckpt = load_checkpoint(tmp_path, domain="keepaway", agent="sarsa")
    rows = ckpt["state"]["records"]["rows"]
    assert ckpt["state"]["agent"]["weight"].shape == (2 * 3, 2**12)
    assert int(ckpt["state"]["records"]["clock"].min()) >= 0.003 * 36000

    _train(
        tmp_path, run_learner, *small, "agent.hours=0.006", "agent.checkpoint_minutes=0.1", checkpoint=ckpt
    )
    again = load_checkpoint(tmp_path)
    assert again["state"]["resumes"] == 1
    assert torch.equal(again["state"]["records"]["rows"][: rows.shape[0]], rows)  # history kept
    assert int(again["state"]["records"]["clock"].min()) >= 0.006 * 36000
    assert len(again["history"]) > len(ckpt["history"])


def test_fields_per_learner_share_tables_and_sum_the_clock(tmp_path, run_learner):
    small = [
        "agent.learners=2",
        "agent.fields_per_learner=3",
        "agent.table_bits=12",
        "agent.log_minutes=0.3",  # one point over 18 of the 21.6 s: every learner has ended episodes in it
    ]
    final = _train(tmp_path, run_learner, *small, "agent.hours=0.006", "agent.checkpoint_minutes=0.1")
    assert final["learners"] == 2
    ckpt = load_checkpoint(tmp_path, domain="keepaway", agent="sarsa")
    state = ckpt["state"]
    assert state["agent"]["weight"].shape == (2 * 3, 2**12)  # tables per learner and keeper
    assert state["agent"]["trace_index"].shape[0] == 2 * 3 * 3  # traces per field and keeper
    clock = state["records"]["clock"]
    assert clock.shape == (6,) and int(clock.view(2, 3).sum(1).min()) >= 0.006 * 36000
    assert int(clock.max()) < 0.006 * 36000  # each field ran about a third of its learner's time
    rows = state["records"]["rows"]
    for learner in range(2):  # ordinals number each learner's episodes over all its fields
        mine = rows[rows[:, 0] // 3 == learner]
        assert mine[:, 1].sort().values.tolist() == list(range(mine.shape[0]))
        assert bool((mine[1:, 2] >= mine[:-1, 2]).all())  # learner clock at the end, nondecreasing
    assert int(state["records"]["episodes"].sum()) == rows.shape[0]

    _train(
        tmp_path, run_learner, *small, "agent.hours=0.009", "agent.checkpoint_minutes=0.1", checkpoint=ckpt
    )
    again = load_checkpoint(tmp_path)["state"]["records"]
    assert torch.equal(again["rows"][: rows.shape[0]], rows)
    assert int(again["clock"].view(2, 3).sum(1).min()) >= 0.009 * 36000


def test_make_sarsa_keepers_maps_fields_to_their_learners_tables():
    config = KeepawayConfig()
    agent = make_sarsa_keepers(config, 2, fields_per_learner=3, size=2**10)
    assert agent.learners == 2 * 3 * 3 and agent.coder.learners == 2 * 3
    field, keeper = torch.arange(18) // 3, torch.arange(18) % 3
    assert torch.equal(agent.tables, (field // 3) * 3 + keeper)
    shared = make_sarsa_keepers(config, 2, fields_per_learner=3, size=2**10, share_weights=True)
    assert shared.coder.learners == 2 and torch.equal(shared.tables, field // 3)


@LEARNERS
def test_simultaneous_updates_of_one_table_add_up(learner):
    """Two rows that share a weight table and decide in the same call: the table moves by the sum of
    the two updates, each computed from the weights before the call (not one after the other)."""
    widths = keepaway_tile_widths()
    gen = torch.Generator().manual_seed(9)
    start = torch.rand(1, 2**10, generator=gen, dtype=torch.float64)
    obs = [torch.rand(2, 13, generator=gen) * 15 for _ in range(2)]
    mask = torch.ones(2, 3, dtype=torch.bool)

    def agent(rows: int) -> SarsaLambda:
        coder = TileCoding(widths, 3, learners=1, size=2**10, dtype=torch.float64)
        coder.weight.copy_(start)
        return learner(coder, epsilon=0.0, tables=torch.zeros(rows, dtype=torch.int64))

    both = agent(2)
    both.start_episode(torch.arange(2), obs[0], mask)
    both.step(torch.arange(2), torch.tensor([3.0, 5.0]), obs[1], mask)
    change = torch.zeros_like(start)
    for i in range(2):
        one = agent(1)
        one.start_episode(ONE, obs[0][i : i + 1], mask[:1])
        one.step(ONE, torch.tensor([3.0, 5.0])[i : i + 1], obs[1][i : i + 1], mask[:1])
        change += one.coder.weight - start
    assert torch.allclose(both.coder.weight - start, change, rtol=0, atol=1e-12)
