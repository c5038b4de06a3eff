"""Every loop that takes feedback fuses through the one component (``hfrl_torch.fusion.Fusion``).

Two checks per loop, run through ``train.py``'s loop on tiny budgets:

- a spy counts the rows each loop hands to ``Fusion.fuse``: one per decision it made;
- with the component's rule replaced by one that always prefers the last choosable action, every action the
  loop takes is that one. A loop that fused, or chose, anywhere else would fail it.
"""

from __future__ import annotations

import pytest
import torch

from hfrl_torch import keys
from hfrl_torch.agents.cem import fused_rollout
from hfrl_torch.envs.tetris.env import TetrisEnv
from hfrl_torch.fusion import Fusion, choosable

TETRIS = ["domain.width=6", "domain.height=6", "domain.max_pieces=40"]
CE = [
    *TETRIS,
    "agent.population=6",
    "agent.games_per_candidate=1",
    "agent.eval_games=2",
    "agent.watch_pieces=20",
]
KEEPAWAY = ["domain=keepaway", "agent.learners=2", "agent.table_bits=12", "agent.log_minutes=0.1"]
LOOPS = {
    "tamer": ["agent=tamer", "trainer=oracle", "agent.games=2", "agent.learners=2", *TETRIS],
    "pg": ["agent=pg", "fusion=linear", "agent.games=2", "agent.learners=2", "agent.eval_games=0", *TETRIS],
    "cem": ["agent=cem", "fusion=linear", "fusion.weight=trust", "agent.iterations=2", *CE],  # 2 plays a step
    "sarsa": [*KEEPAWAY, "fusion=linear", "agent.hours=0.002", "agent.epsilon=0"],
}


@pytest.fixture
def fused_rows(monkeypatch) -> list[int]:
    """The number of rows of every ``Fusion.fuse`` call."""
    rows: list[int] = []
    original = Fusion.fuse

    def spy(self, td, *args, **kwargs):
        rows.append(td.batch_size[0])
        return original(self, td, *args, **kwargs)

    monkeypatch.setattr(Fusion, "fuse", spy)
    return rows


@pytest.fixture
def tetris_actions(monkeypatch) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(action, choosable mask) of every Tetris env step."""
    steps: list[tuple[torch.Tensor, torch.Tensor]] = []
    original = TetrisEnv._step

    def spy(self, td):
        keep = choosable(td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL])
        steps.append((td[keys.ACTION].clone(), keep.clone()))
        return original(self, td)

    monkeypatch.setattr(TetrisEnv, "_step", spy)
    return steps


def _last_choosable(self, r, h, mask, terminal, learner, w):
    """A stand-in rule: the last choosable action is worth far more than any other."""
    keep = choosable(mask, terminal)
    last = keep.shape[-1] - 1 - keep.flip(-1).to(torch.int8).argmax(-1)
    return torch.nn.functional.one_hot(last, keep.shape[-1]).to(torch.float64) * 1e4


@pytest.mark.parametrize("agent", ["tamer", "pg"])
def test_tetris_games_learners_fuse_every_placement(tmp_path, run_learner, fused_rows, tetris_actions, agent):
    learner, _ = run_learner(tmp_path, *LOOPS[agent])
    placements = learner.placement
    assert placements > 0 and fused_rows == [learner.learners] * placements
    assert len(tetris_actions) == placements


@pytest.mark.parametrize("agent", ["tamer", "pg"])
def test_tetris_games_learners_act_on_the_components_values(
    tmp_path, run_learner, monkeypatch, tetris_actions, agent
):
    monkeypatch.setattr(Fusion, "values", _last_choosable)
    run_learner(tmp_path, *LOOPS[agent])
    for action, keep in tetris_actions:
        last = keep.shape[-1] - 1 - keep.flip(-1).to(torch.int8).argmax(-1)
        assert torch.equal(action, last)


def test_ce_with_a_trainer_fuses_the_watched_game_and_hands_its_fusion_to_the_compiled_games(
    tmp_path, run_learner, monkeypatch, fused_rows, tetris_actions
):
    handed: list[Fusion] = []
    original = fused_rollout.play_fused

    def spy(*args, **kwargs):
        handed.append(args[5])
        return original(*args, **kwargs)

    monkeypatch.setattr(fused_rollout, "play_fused", spy)
    learner, _ = run_learner(tmp_path, *LOOPS["cem"])
    assert fused_rows == [1] * len(tetris_actions) and len(tetris_actions) > 0  # the watched games
    assert handed and all(f is learner.fusion for f in handed)  # CE steps and tests: 2 calls an iteration
    assert len(handed) == 2 * 2


def test_ce_with_a_trainer_acts_on_the_components_values(tmp_path, run_learner, monkeypatch, tetris_actions):
    monkeypatch.setattr(Fusion, "values", _last_choosable)
    run_learner(tmp_path, *LOOPS["cem"])
    assert tetris_actions
    for action, keep in tetris_actions:
        assert torch.equal(action, keep.shape[-1] - 1 - keep.flip(-1).to(torch.int8).argmax(-1))


def test_keepaway_keepers_fuse_every_decision_and_act_on_it(tmp_path, run_learner, monkeypatch, fused_rows):
    learner, _ = run_learner(tmp_path / "spy", *LOOPS["sarsa"])
    decisions = int(learner.records.table[:, 5:].sum() + learner.records.decisions.sum())
    assert decisions > 20 and sum(fused_rows) == decisions
    monkeypatch.setattr(Fusion, "values", _last_choosable)
    learner, _ = run_learner(tmp_path / "forced", *LOOPS["sarsa"])
    holds = int(learner.records.table[:, 4].sum() + learner.records.holds.sum())
    assert holds == 0  # every decision took the last action (a pass), none held


def test_keepaway_reward_shaping_goes_through_the_component(tmp_path, run_learner, monkeypatch):
    calls: list[int] = []
    original = Fusion.reward

    def spy(self, reward, human, w):
        calls.append(reward.numel())
        return original(self, reward, human, w)

    monkeypatch.setattr(Fusion, "reward", spy)
    run_learner(tmp_path, *KEEPAWAY, "fusion=reward_shaping", "agent.hours=0.005")
    assert len(calls) > 20  # every env step's rewards (and the episodes' last ones)


DQN_TETRIS = [
    "agent=dqn",
    "fusion=linear",
    "trainer=oracle",
    *TETRIS,
    "agent.boards=3",
    "agent.frames=60",
    "agent.eval_every=60",
    "agent.eval_episodes=2",
    "agent.eval_max_pieces=10",
    "agent.learn_after=30",
    "agent.batch_size=8",
    "agent.cells=[8]",
    "agent.epsilon_start=0",
    "agent.epsilon_end=0",
]
DQN_KEEPAWAY = [
    "agent=dqn",
    "domain=keepaway",
    "trainer=oracle",
    "agent.boards=3",
    "agent.frames=36",
    "agent.eval_every=36",
    "agent.eval_episodes=1",
    "agent.learn_after=12",
    "agent.batch_size=8",
    "agent.cells=[8]",
    "agent.epsilon_start=0",
    "agent.epsilon_end=0",
]


@pytest.mark.parametrize("human", ["linear", "mlp"])
def test_tetris_dqn_fuses_every_collected_placement_and_acts_on_it(
    tmp_path, run_learner, monkeypatch, fused_rows, tetris_actions, human
):
    learner, _ = run_learner(tmp_path / "spy", *DQN_TETRIS, f"human={human}")
    collected = [r for r in fused_rows if r == learner.boards]
    assert len(collected) >= learner.frames // learner.boards  # the collector's steps (and the evaluations')
    monkeypatch.setattr(Fusion, "values", _last_choosable)
    tetris_actions.clear()
    run_learner(tmp_path / "forced", *DQN_TETRIS, f"human={human}")
    assert len(tetris_actions) >= 20
    for action, keep in tetris_actions:  # training (epsilon 0) and the greedy evaluations
        assert torch.equal(action, keep.shape[-1] - 1 - keep.flip(-1).to(torch.int8).argmax(-1))


@pytest.mark.parametrize("fusion", ["linear"])
def test_keepaway_dqn_fuses_every_decision_and_acts_on_it(tmp_path, run_learner, monkeypatch, fusion):
    from hfrl_torch.envs.keepaway import KeepawayEnv

    taken: list[torch.Tensor] = []
    original = KeepawayEnv._step

    def spy(self, td):
        deciding = td[keys.DECIDING]
        taken.append(td[keys.ACTION][deciding].clone())
        return original(self, td)

    monkeypatch.setattr(KeepawayEnv, "_step", spy)
    monkeypatch.setattr(Fusion, "values", _last_choosable)
    run_learner(tmp_path, *DQN_KEEPAWAY, f"fusion={fusion}", "human=mlp")
    actions = torch.cat(taken)
    assert actions.numel() >= 36 and bool(
        (actions == 2).all()
    )  # the last action: a pass to the farther keeper


@pytest.mark.parametrize("weight", ["0.5", "adaptive", "trust"])
def test_dqn_reward_shaping_goes_through_the_component_with_every_weight(
    tmp_path, run_learner, monkeypatch, weight
):
    calls: list[int] = []
    original = Fusion.reward

    def spy(self, reward, human, w):
        calls.append(reward.numel())
        return original(self, reward, human, w)

    monkeypatch.setattr(Fusion, "reward", spy)
    learner, _ = run_learner(tmp_path, *DQN_KEEPAWAY, "fusion=reward_shaping", f"fusion.weight={weight}")
    assert len(calls) >= learner.frames // learner.boards  # every collected step's rewards
    assert learner.episodes > 0
