"""One root seed per run, one stream per component: no two components of a run share a stream."""

from __future__ import annotations

import torch

from hfrl_torch.common.seeding import STREAMS, component_seed


def test_every_component_has_its_own_seed_for_roots_up_to_10000():
    roots = range(10_001)
    seeds = {name: [component_seed(r, name) for r in roots] for name in STREAMS}
    for i, root in enumerate(roots):
        at_root = [seeds[name][i] for name in STREAMS]
        assert len(set(at_root)) == len(STREAMS), f"root {root}: two components share a seed"


def test_a_resumed_env_and_a_later_cem_iteration_meet_no_other_stream():
    for root in (0, 1, 7, 10_000):
        fixed = {component_seed(root, name) for name in STREAMS}
        assert not fixed & {component_seed(root, "env", n) for n in range(1, 4)}
        for t in range(1, 4):
            later = {component_seed(root, name, t) for name in STREAMS if name.startswith("cem_")}
            assert len(later) == 4 and not later & fixed


def test_seeds_the_documented_results_used_are_kept():
    # the agent's, the env's and the CE method's draws are those of the seeding before this table
    assert [component_seed(3, n) for n in ("env", "agent", "timing", "fusion", "bandit")] == [3, 7, 8, 11, 13]
    g = torch.Generator().manual_seed(3 * 1_000_003 + 2 * 7919 + 1)
    assert component_seed(3, "cem_games", 2) == int(torch.randint(0, 2**62, (1,), generator=g))


def test_the_pg_agent_and_its_oracle_trainer_draw_differently(tmp_path):
    from hfrl_torch.experiment.cli import compose_train
    from hfrl_torch.experiment.registry import learner_for

    cfg = compose_train(
        "agent=pg", "trainer=oracle", "logger.backend=none", "agent.learners=2", "agent.games=2"
    )
    learner = learner_for(cfg.agent.name, cfg.domain.name)(cfg, tmp_path)
    oracle = learner.trainer.trainer  # the oracle inside its human-like timing
    agent_draws = torch.rand(8, generator=learner.pg.generator)
    trainer_draws = torch.rand(8, generator=oracle.generator)
    assert not torch.equal(agent_draws, trainer_draws)
