"""One saved-policy schema and one loader table: every registered learner's policy loads through
``load_policy`` to a TorchRL module that acts on its domain's env; unknown kinds are refused in one line;
checkpoints saved before the schema still load."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from tensordict.nn import TensorDictModuleBase

from hfrl_torch import keys
from hfrl_torch.agents.policies import POLICY_LOADERS, export_policy, load_policy, policy_kind
from hfrl_torch.common.checkpoint import load_checkpoint, save_checkpoint
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.common.logger import Logger
from hfrl_torch.envs.gym_task import make_gym_batch
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.experiment.factories import make_gym_task
from hfrl_torch.experiment.registry import LEARNERS, learner_for

TETRIS = ["domain.width=6", "domain.height=8", "logger=none"]
KEEPAWAY = ["domain=keepaway", "logger=none"]
DQN = ["agent=dqn", "agent.boards=2", "agent.cells=[8]", "agent.eval_episodes=2"]
TAUGHT_DQN = ["trainer=oracle", "fusion=linear", "human=mlp", "human.cells=[8]"]
SARSA = ["agent=sarsa", "agent.learners=2", "agent.table_bits=10", "agent.hours=0.05"]
GYM = ["domain=gym", "logger=none", "trainer.reference=examples.cartpole:reference"]
PPO = ["agent=ppo", "agent.boards=2", "agent.cells=[8]", "agent.eval_episodes=2", "agent.minibatch_size=8"]

# (case, overrides, the kind its checkpoint's policy has): every registered learner, taught or not
CASES = [
    ("cem", [*TETRIS, "agent=cem", "trainer=none", "fusion=none"], "linear"),
    ("cem_fused", [*TETRIS, "agent=cem", "trainer=oracle", "fusion=linear"], "fused"),
    ("tamer", [*TETRIS, "agent=tamer", "trainer=oracle", "agent.learners=2"], "linear"),
    ("qlearning", [*TETRIS, "agent=qlearning", "agent.learners=2"], "linear"),
    ("pg", [*TETRIS, "agent=pg", "agent.learners=2"], "linear"),
    ("tetris_dqn", [*TETRIS, *DQN], "tetris_dqn"),
    ("tetris_dqn_fused", [*TETRIS, *DQN, *TAUGHT_DQN], "tetris_dqn"),
    ("sarsa", [*KEEPAWAY, *SARSA, "trainer=none", "fusion=none"], "tile_sarsa"),
    ("sarsa_fused", [*KEEPAWAY, *SARSA, "trainer=oracle", "fusion=linear", "human=tile_coded"], "tile_sarsa"),
    ("keepaway_dqn", [*KEEPAWAY, *DQN], "keepaway_dqn"),
    ("keepaway_dqn_fused", [*KEEPAWAY, *DQN, *TAUGHT_DQN], "keepaway_dqn"),
    (
        "keepaway_dqn_tiles",
        [*KEEPAWAY, *DQN, "trainer=oracle", "fusion=linear", "human=tile_coded"],
        "keepaway_dqn",
    ),
    ("gym_dqn", [*GYM, *DQN], "gym_dqn"),
    ("gym_dqn_fused", [*GYM, *DQN, *TAUGHT_DQN], "gym_dqn"),
    ("gym_tamer", [*GYM, "agent=tamer", "trainer=oracle", "agent.boards=2", "human.cells=[8]"], "gym_tamer"),
    ("gym_ppo", [*GYM, *PPO], "gym_ppo"),
    ("gym_ppo_fused", [*GYM, *PPO, *TAUGHT_DQN], "gym_ppo"),
]


def _saved(tmp_path: Path, compose_train, overrides: list[str]) -> dict:
    """The checkpoint a fresh learner of ``overrides`` writes, saved and read back as evaluate.py reads it."""
    cfg = compose_train(*overrides)
    learner = learner_for(cfg.agent.name, cfg.domain.name)(cfg, tmp_path / "run", None)
    learner.start(Logger())  # what train.py does before the first save
    payload = {"history": [], **learner.checkpoint()}
    path = save_checkpoint(
        tmp_path / "last.pt",
        domain=cfg.domain.name,
        agent=cfg.agent.name,
        config_yaml=OmegaConf.to_yaml(cfg),
        payload=payload,
    )
    return load_checkpoint(path)


def _observation(ckpt: dict, info: dict, boards: int = 3):
    """A first observation of the checkpoint's domain, from the env the policy plays."""
    if ckpt["domain"] == "tetris":
        width = info["board_width"]
        env = TetrisEnv(boards, TetrisRules(width, 8), features=info["env_features"], engine="numba")
        env.set_seed(0)
        return env.reset(), None
    if ckpt["domain"] == "gym":
        env = make_gym_batch(make_gym_task(OmegaConf.create({"domain": info["task"]})), boards, seed=0)
        td = env.reset()
        return td.set(keys.ACTION_MASK, torch.ones(boards, env.action_spec.space.n, dtype=torch.bool)), None
    config = KeepawayConfig(**ckpt["domain_config"])
    return KeepawayEnv(boards, config, seed=0, sync="all").reset(), config


def test_the_cases_cover_every_registered_learner(compose_train):
    covered = set()
    for _, overrides, _ in CASES:
        cfg = compose_train(*overrides)
        covered.add((cfg.domain.name, cfg.agent.name))
    assert covered == set(LEARNERS)
    assert {kind for *_, kind in CASES} == set(POLICY_LOADERS)


@pytest.mark.parametrize(("case", "overrides", "kind"), CASES, ids=[c[0] for c in CASES])
def test_every_learners_saved_policy_loads_to_a_module_that_acts(
    tmp_path, compose_train, case, overrides, kind
):
    ckpt = _saved(tmp_path, compose_train, overrides)
    assert ckpt["policy"]["kind"] == kind == policy_kind(ckpt)
    module, info = load_policy(ckpt, "cpu", torch.Generator().manual_seed(0))
    assert isinstance(module, TensorDictModuleBase) and info["kind"] == kind
    assert keys.ACTION in module.out_keys
    td, _ = _observation(ckpt, info)
    action = module(td.clone())[keys.ACTION]
    assert action.shape == (3,) and action.dtype == torch.int64
    mask = td[keys.ACTION_MASK]
    assert bool(mask.gather(1, action.view(-1, 1)).all())  # only actions the env allows
    # the direct form the domain's batched player takes, where there is one
    direct = {"tetris": "afterstate", "keepaway": "chooser"}.get(ckpt["domain"])
    assert (direct is None or info[direct] is None) == kind.endswith(("_dqn", "_ppo", "_tamer"))


def test_the_linear_module_chooses_the_best_safe_placement(tmp_path, compose_train):
    ckpt = _saved(tmp_path, compose_train, CASES[0][1])
    module, info = load_policy(ckpt)
    td, _ = _observation(ckpt, info, boards=4)
    w = info["afterstate"]["weights"]
    values = td[keys.AFTERSTATE_FEATURES].to(torch.float64) @ w
    ok = td[keys.ACTION_MASK] & ~td[keys.AFTERSTATE_TERMINAL]
    best = values.masked_fill(~ok, -torch.inf).argmax(-1)
    assert torch.equal(module(td.clone())[keys.ACTION], best)


def test_the_keeper_module_plays_as_its_chooser(tmp_path, compose_train):
    ckpt = _saved(tmp_path, compose_train, CASES[8][1])  # sarsa with H^ fused
    module, info = load_policy(ckpt, "cpu", torch.Generator().manual_seed(5))
    td, _ = _observation(ckpt, info, boards=4)
    acted = module(td.clone())[keys.ACTION]
    _, again = load_policy(ckpt, "cpu", torch.Generator().manual_seed(5))
    chosen = again["chooser"](td[keys.OBSERVATION], td[keys.ACTION_MASK], td[keys.KEEPER])
    assert torch.equal(acted, chosen)


@pytest.mark.parametrize("bad", ["bogus", 7, None])
def test_an_unknown_kind_is_refused_in_one_line_naming_it_and_the_allowed(bad):
    ckpt = {"domain": "keepaway", "path": "run/last.pt", "policy": {"kind": bad}}
    with pytest.raises(CheckpointError) as e:
        load_policy(ckpt)
    message = str(e.value)
    assert "\n" not in message and repr(bad) in message and "run/last.pt" in message
    allowed = "fused, gym_dqn, gym_ppo, gym_tamer, keepaway_dqn, linear, tetris_dqn, tile_sarsa"
    assert f"allowed: {allowed}" in message


def test_export_refuses_a_kind_nothing_loads():
    with pytest.raises(ValueError, match="policy kind 'bogus' has no loader; allowed: fused"):
        export_policy("bogus", weights=torch.zeros(3))


def test_a_policy_its_loader_cannot_read_is_one_line(tmp_path, compose_train):
    ckpt = _saved(tmp_path, compose_train, CASES[5][1])  # tetris DQN
    ckpt["policy"]["cells"] = [3, 3]  # not the saved network's shape
    with pytest.raises(CheckpointError, match="Q network does not load") as e:
        load_policy(ckpt)
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("case", [5, 6, 9, 10, 11], ids=lambda i: CASES[i][0])
def test_a_legacy_dqn_checkpoint_loads_by_its_domain(tmp_path, compose_train, case):
    """Both DQN learners wrote kind "dqn" before a kind named its loader."""
    ckpt = _saved(tmp_path, compose_train, CASES[case][1])
    legacy = dict(ckpt, policy=dict(ckpt["policy"], kind="dqn"))
    path = save_checkpoint(
        tmp_path / "legacy.pt",
        domain=legacy["domain"],
        agent=legacy["agent"],
        config_yaml=legacy["config"],
        payload={
            k: v
            for k, v in legacy.items()
            if k not in ("format", "version", "domain", "agent", "config", "path")
        },
    )
    legacy = load_checkpoint(path)
    module, info = load_policy(legacy)
    assert info["kind"] == CASES[case][2]
    td, _ = _observation(legacy, info)
    new_module, _ = load_policy(ckpt)
    assert torch.equal(module(td.clone())[keys.ACTION], new_module(td.clone())[keys.ACTION])


def test_a_legacy_kindless_tetris_policy_loads_as_linear(tmp_path, compose_train):
    """The earliest Tetris policy form: features and weights, no kind (evaluate.py played it linear)."""
    ckpt = _saved(tmp_path, compose_train, CASES[0][1])
    legacy = dict(ckpt, policy={k: v for k, v in ckpt["policy"].items() if k != "kind"})
    _, info = load_policy(legacy)
    assert info["kind"] == "linear"
    assert torch.equal(info["afterstate"]["weights"], torch.as_tensor(ckpt["policy"]["weights"]).double())
    # a kind-less dict that is not that form is refused, naming None
    with pytest.raises(CheckpointError, match="kind None; allowed"):
        load_policy(dict(ckpt, policy={"note": "?"}))
