"""The compiled Sarsa(lambda) learner and H^ against the torch reference: tile indices bit for bit, the
same actions on scripted episodes (several learners, shared tables, starting, continuing and ending rows,
lambda 0 and 0.9, fused values to choose by) with weights, Q_LastAction and traces within float32
rounding, full trace slots, and the choice of path with its errors."""

from __future__ import annotations

import numba
import pytest
import torch
from omegaconf import OmegaConf

from hfrl_torch.agents.sarsa import (
    SarsaLambda,
    SarsaLambdaNumba,
    resolve_learner_kernels,
    sarsa_keepers,
)
from hfrl_torch.agents.sarsa.sarsa_numba import MIN_ROWS_PER_THREAD, _sort_tiles
from hfrl_torch.agents.tamer.keeper_tamer import KeeperTamer
from hfrl_torch.common.errors import ConfigError
from hfrl_torch.common.threads import thread_count
from hfrl_torch.envs.keepaway import KeepawayConfig
from hfrl_torch.experiment.checks import check_learner_kernels
from hfrl_torch.experiment.factories import make_keepers
from hfrl_torch.models.tile_coding import TileCoding, keepaway_tile_widths
from hfrl_torch.models.tile_coding_numba import compiled_add_, compiled_values, tile_indices

pytestmark = pytest.mark.usefixtures("one_thread")

WIDTHS = keepaway_tile_widths()
TOL = {"rtol": 1e-5, "atol": 1e-5}


@pytest.mark.parametrize(
    ("size", "tilings", "scale"), [(2**20, 32, 20.0), (1000, 7, 1e4), (1, 32, 5.0), (2**30, 32, 1e16)]
)
def test_tile_indices_equal_torch_bit_for_bit(size, tilings, scale):
    gen = torch.Generator().manual_seed(size)
    coder = TileCoding(WIDTHS, 3, tilings=tilings, size=size)
    obs = (torch.rand(50, 13, generator=gen) * 2 - 0.5) * scale  # negative values too (floor, not truncation)
    obs[0] = torch.tensor(WIDTHS) * 3  # exactly on tile boundaries
    tiles = tile_indices(obs.to(torch.float64).numpy(), coder.widths.numpy(), tilings, 3, size)
    assert torch.equal(torch.from_numpy(tiles), coder.tiles(obs))  # 1e16: int64 keys wrap alike


def test_tile_sort():
    gen = torch.Generator().manual_seed(0)
    for top in (1, 2**11, 2**20, 2**30):
        tiles = torch.randint(0, top, (1248,), generator=gen)
        assert torch.equal(torch.from_numpy(_sort_tiles(tiles.numpy())), tiles.sort().values)


def test_compiled_sums_and_adds_match_torch():
    gen = torch.Generator().manual_seed(1)
    coder = TileCoding(WIDTHS, 3, learners=4, size=2**12)
    coder.weight.copy_(torch.randn(4, 2**12, generator=gen))
    tables, tiles = torch.tensor([3, 0, 3, 1]), coder.tiles(torch.rand(4, 13, generator=gen) * 20)
    assert torch.allclose(compiled_values(coder, tables, tiles), coder(tables, tiles), **TOL)
    step = torch.randn(4, generator=gen, dtype=torch.float64)
    other = TileCoding(WIDTHS, 3, learners=4, size=2**12)
    other.weight.copy_(coder.weight)
    compiled_add_(coder, tables, tiles[:, 1], step)  # rows 0 and 2 share table 3: their adds sum
    other.add_(tables, tiles[:, 1], step.unsqueeze(1).expand(-1, tiles.shape[-1]))
    assert torch.equal(coder.weight, other.weight)  # the same float32 adds in the same order


def _pair(lambda_: float, **kwargs) -> tuple[SarsaLambda, SarsaLambda]:
    """A torch and a compiled learner: six learners on three tables (learners l and l + 3 share one)."""

    def one(cls: type[SarsaLambda]) -> SarsaLambda:
        coder = TileCoding(WIDTHS, 3, learners=3, size=2**12)
        tables = torch.tensor([0, 1, 2, 0, 1, 2])
        return cls(coder, alpha=0.125, epsilon=0.2, lambda_=lambda_, seed=3, tables=tables, **kwargs)

    return one(SarsaLambda), one(SarsaLambdaNumba)


def _traces(agent: SarsaLambda, learner: int) -> dict[int, float]:
    live = agent.trace_value[learner] > 0
    index, value = agent.trace_index[learner][live].tolist(), agent.trace_value[learner][live].tolist()
    return dict(zip(index, value, strict=True))


def _assert_same_state(torch_agent: SarsaLambda, compiled: SarsaLambda, same_layout: bool) -> None:
    assert torch.equal(torch_agent.last_action, compiled.last_action)
    assert torch.allclose(torch_agent.coder.weight, compiled.coder.weight, **TOL)
    assert torch.allclose(torch_agent.q_last, compiled.q_last, **TOL)
    for learner in range(torch_agent.learners):
        ours, theirs = _traces(torch_agent, learner), _traces(compiled, learner)
        assert ours.keys() == theirs.keys()
        assert all(abs(ours[k] - theirs[k]) < 1e-6 for k in ours)
    if same_layout:
        assert torch.equal(torch_agent.trace_index, compiled.trace_index)
        assert torch.equal(torch_agent.trace_value, compiled.trace_value)


@pytest.mark.parametrize(
    ("lambda_", "fused", "ties"),
    [(0.0, False, "random"), (0.0, True, "random"), (0.9, False, "random"), (0.9, True, "random"),
     (0.9, False, "first")],
)  # fmt: skip
def test_scripted_episodes_give_the_same_actions_and_weights(lambda_, fused, ties):
    reference, compiled = _pair(lambda_)
    reference.ties = compiled.ties = ties
    gen = torch.Generator().manual_seed(7)
    for step in range(60):
        m = int(torch.randint(1, 7, (1,), generator=gen))
        learners = torch.randperm(6, generator=gen)[:m]
        obs = (torch.rand(m, 13, generator=gen) * 2 - 0.2) * 8  # near states: tiles and traces overlap
        mask = torch.rand(m, 3, generator=gen) < 0.7
        mask[:, 0] = True
        reward = torch.randint(1, 30, (m,), generator=gen).float()
        if step % 9 == 8:  # some rows end (learners without a pending action are left alone)
            reference.end_episode(learners, reward)
            compiled.end_episode(learners, reward)
            continue
        if fused:
            h = torch.randn(m, 3, generator=gen, dtype=torch.float64)
            explore = bool(step % 2)
            chosen = []
            for agent in (reference, compiled):
                tiles, q = agent.action_values(learners, obs)
                choose_by = torch.where(torch.rand(m, 3, generator=torch.Generator()) < 0.3, 0.0, q + h)
                chosen.append(
                    agent.decide(
                        learners, obs, mask, reward, values=(tiles, q), choose_by=choose_by, explore=explore
                    )
                )
        else:
            chosen = [agent.decide(learners, obs, mask, reward) for agent in (reference, compiled)]
        assert torch.equal(chosen[0], chosen[1])
        assert torch.equal(reference.chosen_tiles, compiled.chosen_tiles)
    _assert_same_state(reference, compiled, same_layout=lambda_ == 0.0)
    assert reference.coder.weight.abs().max() > 0.1  # they learned something
    assert torch.equal(reference.generator.get_state(), compiled.generator.get_state())


def test_a_torch_checkpoint_continues_on_the_compiled_learner():
    reference, compiled = _pair(0.9)
    gen = torch.Generator().manual_seed(2)
    learners, mask = torch.arange(6), torch.ones(6, 3, dtype=torch.bool)
    for _ in range(3):
        reference.decide(learners, torch.rand(6, 13, generator=gen) * 10, mask, torch.ones(6))
    compiled.decide(learners, torch.rand(6, 13, generator=gen) * 10, mask, torch.ones(6))  # views made
    compiled.load_state_dict(reference.state_dict())  # loaded in place: the numpy views see it
    for step in range(4):
        if step == 2:  # replaced tensors: the views are made again
            compiled.trace_value = compiled.trace_value.clone()
            compiled.coder.weight = compiled.coder.weight.clone()
        obs = torch.rand(6, 13, generator=gen) * 10
        assert torch.equal(*(a.decide(learners, obs, mask, torch.ones(6)) for a in (reference, compiled)))
    for agent in (reference, compiled):
        agent.end_episode(learners, torch.full((6,), 4.0))
    _assert_same_state(reference, compiled, same_layout=False)


def test_full_trace_slots_keep_the_same_largest_values():
    reference, compiled = _pair(0.9, max_traces=1000)  # 416 tiles per decision: full after the third
    gen = torch.Generator().manual_seed(5)
    learners, mask = torch.tensor([0]), torch.ones(1, 3, dtype=torch.bool)
    for _ in range(6):  # far-apart states
        obs = torch.rand(1, 13, generator=gen) * 40
        assert torch.equal(*(a.decide(learners, obs, mask, torch.ones(1)) for a in (reference, compiled)))
    values = [agent.trace_value[0].sort(descending=True).values for agent in (reference, compiled)]
    assert torch.allclose(values[0], values[1], rtol=0, atol=1e-6)  # which of equal traces goes may differ
    assert int((values[1] > 0).sum()) == 1000
    chosen = compiled.chosen_tiles[0].unique()
    assert torch.equal(compiled.trace_index[0][compiled.trace_value[0] == 1.0].sort().values, chosen)


def test_compiled_decide_checks_its_rows():
    _, compiled = _pair(0.0)
    mask = torch.ones(2, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match="distinct learners"):
        compiled.decide(torch.tensor([1, 1]), torch.zeros(2, 13), mask, torch.zeros(2))
    with pytest.raises(ValueError, match="expected 13 state variables"):
        compiled.decide(torch.tensor([0, 1]), torch.zeros(2, 12), mask, torch.zeros(2))
    compiled.start_episode(torch.tensor([0]), torch.zeros(1, 13), mask[:1])
    with pytest.raises(ValueError, match="pending action"):
        compiled.start_episode(torch.tensor([0]), torch.zeros(1, 13), mask[:1])


def test_h_hat_values_and_credit_updates_agree():
    gen = torch.Generator().manual_seed(3)
    tamers = []
    for kernels in ("torch", "numba"):
        model = TileCoding(WIDTHS, 3, learners=2, size=2**12)
        tamers.append(KeeperTamer(model, fields=2, alpha=0.5, window=None, history=4, kernels=kernels))
    given = 0
    for t in range(12):
        tiles = tamers[0].model.tiles(torch.rand(2, 13, generator=gen) * 10)
        owner, deciding = torch.tensor([0, 1]), torch.rand(2, generator=gen) < 0.8
        h = [tamer.values(owner, tiles) for tamer in tamers]
        assert torch.allclose(h[0], h[1], **TOL)
        for tamer in tamers:
            tamer.record(deciding, owner, tiles[:, 0], torch.full((2,), 0.2 * t, dtype=torch.float64))
        feedback = torch.tensor([1.0, -1.0]) * (torch.rand(2, generator=gen) < 0.6)
        when = torch.full((2,), 0.2 * t + 0.1, dtype=torch.float64)
        counts = [tamer.give(feedback, when) for tamer in tamers]
        assert counts[0] == counts[1]
        given += counts[0]
    assert given > 0 and tamers[0].model.weight.abs().max() > 1e-3  # alpha / N per tile
    assert torch.allclose(tamers[0].model.weight, tamers[1].model.weight, **TOL)
    with pytest.raises(ValueError, match="kernels='fast' is invalid; allowed: torch, numba"):
        KeeperTamer(TileCoding(WIDTHS, 3), fields=1, kernels="fast")


def test_the_choice_of_path_and_its_errors():
    config = KeepawayConfig()
    assert type(sarsa_keepers(config, 1, size=2**8, kernels="auto")) is SarsaLambdaNumba
    assert type(sarsa_keepers(config, 1, size=2**8, kernels="torch")) is SarsaLambda
    assert resolve_learner_kernels("auto", "cuda") == "torch"
    with pytest.raises(ValueError, match="kernels='numba' runs on the CPU only"):
        resolve_learner_kernels("numba", "cuda")
    with pytest.raises(ValueError, match="kernels='fast' is invalid; allowed: auto, numba, torch"):
        sarsa_keepers(config, 1, size=2**8, kernels="fast")
    cfg = OmegaConf.create({"device": "cpu", "seed": 0, "agent": {"kernels": "numba"}})
    assert check_learner_kernels(cfg) == "numba"
    cfg.agent.kernels = "fast"
    with pytest.raises(ConfigError, match=r"^agent.kernels='fast' is invalid; allowed: auto, numba, torch$"):
        check_learner_kernels(cfg)
    cfg.agent.kernels, cfg.device = "numba", "cuda"
    with pytest.raises(ConfigError, match=r"agent\.kernels='numba' runs on the CPU only, not device=cuda"):
        check_learner_kernels(cfg)
    cfg.agent.kernels = "auto"
    assert check_learner_kernels(cfg) == "auto"


def test_make_keepers_follows_agent_kernels(compose_train):
    for kernels, cls in (("auto", SarsaLambdaNumba), ("numba", SarsaLambdaNumba), ("torch", SarsaLambda)):
        cfg = compose_train(
            "domain=keepaway", "agent=sarsa", "agent.table_bits=8", f"agent.kernels={kernels}"
        )
        assert type(make_keepers(cfg, KeepawayConfig(), torch.device("cpu"))) is cls


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs two numba threads")
@pytest.mark.parametrize("lambda_", [0.0, 0.9])
@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("m", [10, 150])
def test_two_threads_decide_as_one_bit_for_bit(lambda_, fused, m):
    """Above MIN_ROWS_PER_THREAD rows a second thread splits the decision into phases (updates split by
    weight table); rows on shared tables, starting, continuing and ending: the same actions and state."""

    def one() -> SarsaLambdaNumba:
        coder = TileCoding(WIDTHS, 3, learners=5, size=2**12)
        tables = torch.arange(200) % 5  # 40 rows on each table
        return SarsaLambdaNumba(coder, alpha=0.125, epsilon=0.2, lambda_=lambda_, seed=3, tables=tables)

    agents = {threads: one() for threads in (1, 2)}
    gen = torch.Generator().manual_seed(9)
    rows = torch.randperm(200, generator=gen)[:m]
    steps = [(torch.rand(m, 13, generator=gen) * 20, torch.rand(m, 3, generator=gen) * 5) for _ in range(4)]
    mask = torch.ones(m, 3, dtype=torch.bool)
    mask[::7, 2] = False
    for threads, agent in agents.items():
        numba.set_num_threads(threads)
        assert thread_count(m, MIN_ROWS_PER_THREAD) == threads
        for i, (obs, reward) in enumerate(steps):
            values = choose = None
            if fused:
                values = agent.action_values(rows, obs)
                choose = values[1].double() + reward
            agent.decide(rows, obs, mask, reward[:, 0], values=values, choose_by=choose)
            if i == 2:
                agent.end_episode(rows[: m // 3], reward[: m // 3, 1])
    numba.set_num_threads(1)
    one_thread, two_threads = agents[1], agents[2]
    assert thread_count(m, MIN_ROWS_PER_THREAD) == 1  # (back to one thread)
    for name in ("last_action", "q_last", "trace_index", "trace_value"):
        assert torch.equal(getattr(one_thread, name), getattr(two_threads, name)), name
    assert torch.equal(one_thread.coder.weight, two_threads.coder.weight)
    assert torch.equal(one_thread.chosen_tiles, two_threads.chosen_tiles)
    with pytest.raises(ValueError, match="distinct learners"):
        numba.set_num_threads(2)
        try:
            two_threads.decide(
                torch.zeros(100, dtype=torch.int64), steps[0][0][:100], mask[:100], steps[0][1][:100, 0]
            )
        finally:
            numba.set_num_threads(1)
