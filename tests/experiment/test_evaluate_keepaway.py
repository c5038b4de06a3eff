"""evaluate.py domain=keepaway policy=<run dir | checkpoint>: learned keepers played greedily."""

from __future__ import annotations

import copy
import json
import subprocess
from pathlib import Path

import pytest
import torch
from script_runner import run_script

from hfrl_torch.agents.sarsa.policy import load_keeper_policy
from hfrl_torch.common.checkpoint import load_checkpoint, save_checkpoint
from hfrl_torch.common.errors import CheckpointError, ConfigError
from hfrl_torch.envs.keepaway import play_benchmark_policy, play_keeper_policy
from hfrl_torch.experiment.cli import compose_config
from hfrl_torch.experiment.config import validate_train
from hfrl_torch.experiment.keepaway_evaluation import evaluate_keepaway, format_keepaway_summary
from hfrl_torch.experiment.learners.keepaway_sarsa import SarsaKeepers
from hfrl_torch.experiment.run import RunFiles, learn
from hfrl_torch.models.tile_coding import TileCoding

pytestmark = pytest.mark.usefixtures("one_thread")

ROOT = Path(__file__).resolve().parents[2]
SMALL = ["agent.learners=2", "agent.table_bits=12", "agent.hours=0.003"]
KEYS = (
    "domain",
    "policy",
    "preset",
    "keepers",
    "takers",
    "episodes",
    "mean_s",
    "sd_s",
    "median_s",
    "ci95_low",
    "ci95_high",
    "taken_share",
    "out_share",
    "cycles_per_s",
    "teams",
    "per_team_mean_s",
)
OUTCOME = ("mean_s", "sd_s", "median_s", "ci95_low", "ci95_high", "taken_share", "out_share")


def _train(run_dir: Path, *overrides: str) -> Path:
    cfg = compose_config("train", "domain=keepaway", "logger=none", *overrides, *SMALL)
    validate_train(cfg)
    learn(SarsaKeepers(cfg, run_dir), RunFiles(run_dir, cfg))
    return run_dir


@pytest.fixture(scope="module")
def plain(tmp_path_factory) -> Path:
    return _train(tmp_path_factory.mktemp("plain"), "trainer=none", "fusion=none")


@pytest.fixture(scope="module")
def fused(tmp_path_factory) -> Path:
    return _train(tmp_path_factory.mktemp("fused"), "trainer=oracle", "fusion=linear", "human=tile_coded")


def _evaluate(policy: Path | str, *overrides: str) -> dict:
    cfg = compose_config("evaluate", "domain=keepaway", f"policy={policy}", *overrides)
    return evaluate_keepaway(cfg, progress=False)


def test_a_sarsa_checkpoint_plays_greedily_and_reports_per_team(plain, tmp_path):
    gif = tmp_path / "episode.gif"
    res = _evaluate(plain, "episodes=12", "domain.batch=6", "seed=3", f"gif={gif}")
    assert all(key in res for key in KEYS) and res["policy"] == str(plain)
    assert res["domain"] == "keepaway" and res["episodes"] == 12 and (res["keepers"], res["takers"]) == (3, 2)
    assert res["teams"] == 2 and len(res["per_team_mean_s"]) == 2
    # 6 fields x 2 episodes; fields 0, 2, 4 play for team 0: equal shares, so the teams average to the mean
    assert sum(res["per_team_mean_s"]) / 2 == pytest.approx(res["mean_s"])
    assert abs(res["taken_share"] + res["out_share"] - 1.0) < 1e-9 and res["mean_s"] > 0
    assert gif.is_file() and gif.stat().st_size > 1000 and res["gif_episode_s"] > 0
    assert "2 teams, greedy" in format_keepaway_summary(res)
    json.dumps(res, allow_nan=False)

    again = _evaluate(plain / "checkpoints" / "last.pt", "episodes=12", "domain.batch=6", "seed=3")
    assert {k: again[k] for k in OUTCOME} == {k: res[k] for k in OUTCOME}
    assert again["per_team_mean_s"] == res["per_team_mean_s"]
    assert again["policy"] == str(plain / "checkpoints" / "last.pt")


def test_teams_without_a_field_are_reported_as_none(plain):
    res = _evaluate(plain, "episodes=2", "domain.batch=1", "seed=3")
    assert res["per_team_mean_s"][0] == pytest.approx(res["mean_s"]) and res["per_team_mean_s"][1] is None
    assert "1 teams had no field" in format_keepaway_summary(res)


def test_a_checkpoint_is_played_on_the_task_it_learned(fused):
    """The trainer's run learned with 500 ms decisions; the command line's domain (100 ms without a
    trainer) does not apply: the result is the chooser's on the saved task, ties drawn from seed + 1."""
    ckpt = load_checkpoint(fused)
    options = dict(ckpt["domain_config"])
    assert options["decision_period_cycles"] == 5
    res = _evaluate(fused, "episodes=8", "domain.batch=8", "seed=6")
    choose, _ = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(7))
    direct = play_keeper_policy(choose, str(fused), 8, batch=8, seed=6, progress=False, teams=2, **options)
    assert {k: res[k] for k in OUTCOME} == {k: direct[k] for k in OUTCOME}
    assert res["per_team_mean_s"] == direct["per_team_mean_s"]


def _obs_batch(rows: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Plausible 3v2 state variables, holders and masks (every other row without the first pass)."""
    gen = torch.Generator().manual_seed(seed)
    obs = torch.rand(rows, 13, generator=gen) * 15.0
    obs[:, 11:] = torch.rand(rows, 2, generator=gen) * 90.0
    holder = torch.randint(0, 3, (rows,), generator=gen)
    mask = torch.ones(rows, 3, dtype=torch.bool)
    mask[::2, 1] = False
    return obs, holder, mask


def _random_weights(ckpt: dict, seed: int) -> dict:
    ckpt = copy.deepcopy(ckpt)
    gen = torch.Generator().manual_seed(seed)
    state = ckpt["state"]
    state["agent"]["weight"] = torch.randn(state["agent"]["weight"].shape, generator=gen)
    if "human" in state:
        state["human"]["human_weight"] = torch.randn(state["human"]["human_weight"].shape, generator=gen)
    return ckpt


def _values_by_hand(
    ckpt: dict, weight: torch.Tensor, obs: torch.Tensor, tables: torch.Tensor
) -> torch.Tensor:
    p = ckpt["policy"]
    coder = TileCoding(p["tile_widths"], p["num_actions"], weight.shape[0], p["tilings"], p["size"])
    coder.weight.copy_(weight)
    return coder(tables, coder.tiles(obs)).double()


def _argmax(values: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return values.masked_fill(~mask, -torch.inf).argmax(1)


def _rescaled(v: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    lo = v.masked_fill(~mask, torch.inf).amin(1, keepdim=True)
    hi = v.masked_fill(~mask, -torch.inf).amax(1, keepdim=True)
    return (v - lo) / (hi - lo)


def test_the_chooser_takes_the_argmax_of_q(plain):
    ckpt = _random_weights(load_checkpoint(plain), seed=1)
    obs, holder, mask = _obs_batch(64, seed=2)
    team = torch.arange(64) % 2
    q = _values_by_hand(ckpt, ckpt["state"]["agent"]["weight"], obs, team * 3 + holder)
    choose, info = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(0))
    assert info["teams"] == 2 and info["scheme"] == "none" and info["weight"] is None
    actions = choose(obs, mask, holder)
    assert torch.equal(actions, _argmax(q, mask))
    assert not bool(mask.gather(1, actions.unsqueeze(1)).logical_not().any())
    assert len(set(actions.tolist())) == 3  # a batch where every action wins somewhere


@pytest.mark.parametrize(
    ("scheme", "scaling", "weight"),
    [
        ("linear", "none", [0.5, 3.0]),
        ("linear", "decision", [0.5, 3.0]),
        ("linear", "spread", [0.5, 3.0]),
        ("exponential", "decision", [0.5, 2.0]),
        ("exponential", "spread", [0.5, 2.0]),
        ("human_only", "none", [0.5, 0.5]),
        ("control_sharing", "none", [0.3, 0.7]),
        ("none", "none", [5.0, 5.0]),
        ("reward_shaping", "none", [5.0, 5.0]),
    ],
)
def test_a_fused_checkpoint_chooses_by_its_fusion_rule(fused, scheme, scaling, weight):
    ckpt = _random_weights(load_checkpoint(fused), seed=3)
    human = ckpt["policy"]["human"]
    assert human is not None and human["scheme"] == "linear" and human["model"] == "team"
    spread = [0.3, 4.0]
    human.update(scheme=scheme, scaling=scaling, weight=weight, q_spread=spread)
    obs, holder, mask = _obs_batch(64, seed=4)
    team = torch.arange(64) % 2
    q = _values_by_hand(ckpt, ckpt["state"]["agent"]["weight"], obs, team * 3 + holder)
    h = _values_by_hand(ckpt, ckpt["state"]["human"]["human_weight"], obs, team)
    w = torch.tensor(weight, dtype=torch.float64)[team].unsqueeze(1)
    r, hh = (_rescaled(q, mask), _rescaled(h, mask)) if scaling == "decision" else (q, h)
    if scaling == "spread" and scheme != "exponential":  # the exponential rule fuses raw values
        hh = h * torch.tensor(spread, dtype=torch.float64)[team].unsqueeze(1)
    expected = {
        "linear": lambda: _argmax(r + w * hh, mask),
        "exponential": lambda: _argmax(r * (1 + torch.sign(hh) * hh.abs() ** w), mask),
        "human_only": lambda: _argmax(h, mask),
        "control_sharing": lambda: torch.where(team == 1, _argmax(h, mask), _argmax(q, mask)),
        "none": lambda: _argmax(q, mask),
        "reward_shaping": lambda: _argmax(q, mask),
    }[scheme]()
    choose, info = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(0))
    assert info["scheme"] == scheme and info["weight"] == weight
    assert torch.equal(choose(obs, mask, holder), expected)
    if scheme in ("linear", "human_only", "control_sharing"):
        assert not torch.equal(expected, _argmax(q, mask))  # the rule matters on this batch


def test_ties_are_broken_at_random_from_the_generator(plain):
    ckpt = copy.deepcopy(load_checkpoint(plain))
    ckpt["state"]["agent"]["weight"].zero_()
    obs, holder, mask = _obs_batch(200, seed=5)
    choose, _ = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(7))
    first = choose(obs, mask, holder)
    assert set(first[::2].tolist()) == {0, 2} and set(first[1::2].tolist()) == {0, 1, 2}
    again, _ = load_keeper_policy(ckpt, "cpu", torch.Generator().manual_seed(7))
    assert torch.equal(again(obs, mask, holder), first)


def test_a_checkpoint_that_always_holds_plays_exactly_like_always_hold(plain, tmp_path):
    """Q(hold) is made the largest in every state that Always Hold visits (weight 1 on the hold tiles of
    those states, 0 elsewhere, in a table large enough that the passes' tiles rarely share them), so the
    greedy keepers hold in every decision and, with the same seed, play the very same episodes."""
    ckpt = load_checkpoint(plain)
    options = dict(ckpt["domain_config"])
    run = {"batch": 8, "seed": 11, "progress": False}
    seen: list[torch.Tensor] = []

    def hold_and_record(obs: torch.Tensor, mask: torch.Tensor, holder: torch.Tensor) -> torch.Tensor:
        seen.append(obs.clone())
        return torch.zeros(obs.shape[0], dtype=torch.long)

    recorded = play_keeper_policy(hold_and_record, "hold", 8, **run, **options)
    hold = play_benchmark_policy("hold", 8, **run, **options)
    assert {k: recorded[k] for k in OUTCOME} == {k: hold[k] for k in OUTCOME}

    policy = dict(ckpt["policy"], size=2**20)
    coder = TileCoding(policy["tile_widths"], policy["num_actions"], 6, policy["tilings"], policy["size"])
    tiles = coder.tiles(torch.cat(seen))
    weight = torch.zeros(6, policy["size"])
    weight[:, tiles[:, 0].unique()] = 1.0
    payload = {k: ckpt[k] for k in ("history", "domain_config")}
    state = {"agent": {"weight": weight}}
    path = save_checkpoint(
        tmp_path / "hold.pt",
        domain="keepaway",
        agent="sarsa",
        config_yaml=ckpt["config"],
        payload={**payload, "state": state, "policy": policy},
    )
    res = _evaluate(path, "episodes=8", "domain.batch=8", "seed=11")
    assert {k: res[k] for k in OUTCOME} == {k: hold[k] for k in OUTCOME}


def test_bad_checkpoints_give_one_line_errors(plain, tmp_path):
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(
        bytes(torch.randint(0, 256, (4096,), generator=torch.Generator().manual_seed(0)).tolist())
    )
    with pytest.raises(CheckpointError, match="is corrupt or not a torch checkpoint") as info:
        _evaluate(corrupt, "episodes=4")
    assert str(corrupt) in str(info.value) and "\n" not in str(info.value)

    tetris = save_checkpoint(
        tmp_path / "tetris.pt", domain="tetris", agent="cem", config_yaml="", payload={"policy": {}}
    )
    with pytest.raises(CheckpointError, match="is for domain 'tetris', not 'keepaway'") as info:
        _evaluate(tetris, "episodes=4")
    assert str(tetris) in str(info.value) and "\n" not in str(info.value)

    empty = tmp_path / "empty_run"
    empty.mkdir()
    with pytest.raises(CheckpointError, match="does not exist"):
        _evaluate(empty, "episodes=4")
    with pytest.raises(ConfigError, match="allowed: hand, random, hold, or a keepaway run directory"):
        _evaluate(tmp_path / "no_such_run", "episodes=4")

    ckpt = load_checkpoint(plain)
    broken = save_checkpoint(
        tmp_path / "broken.pt",
        domain="keepaway",
        agent="sarsa",
        config_yaml=ckpt["config"],
        payload={"state": {}, "policy": ckpt["policy"], "domain_config": ckpt["domain_config"]},
    )
    with pytest.raises(CheckpointError, match="holds no playable keepaway policy"):
        _evaluate(broken, "episodes=4")


def _cli(*args: str) -> subprocess.CompletedProcess:
    """``python evaluate.py <args>`` as a user types it, forked from a process that has made its imports."""
    return run_script("evaluate.py", *args, timeout=300)


def test_the_cli_plays_a_run_directory(plain):
    out = _cli("domain=keepaway", f"policy={plain}", "episodes=20", "domain.batch=20")
    assert out.returncode == 0, out.stderr[-2000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["policy"] == str(plain) and res["episodes"] == 20 and res["teams"] == 2
    assert all(key in res for key in KEYS) and "2 teams, greedy" in out.stdout


def test_task_values_on_the_command_line_are_refused_for_a_checkpoint(plain, monkeypatch):
    """evaluate.py domain=keepaway policy=<run> domain.keepers=4: refused rather than silently ignored."""
    overrides = ["domain=keepaway", f"policy={plain}", "domain.batch=4", "domain.keepers=4"]
    monkeypatch.setattr("hfrl_torch.experiment.keepaway_evaluation.task_overrides", lambda: overrides)
    with pytest.raises(ConfigError) as info:
        _evaluate(plain, "episodes=4", "domain.batch=4", "domain.keepers=4")
    assert str(info.value) == (
        "domain.keepers=4 does not apply to a checkpoint, which is played on the task it learned "
        "(set only domain.batch, domain.kernels, episodes and seed)"
    )


def test_a_checkpoint_plays_alike_with_either_kernels(plain, monkeypatch):
    """domain.kernels says how the simulator runs, not what task: allowed for a checkpoint, same bits."""
    monkeypatch.setattr(
        "hfrl_torch.experiment.keepaway_evaluation.task_overrides",
        lambda: ["domain.batch=4", "domain.kernels=torch"],
    )
    runs = [
        _evaluate(plain, "episodes=4", "domain.batch=4", f"domain.kernels={k}") for k in ("torch", "numba")
    ]
    assert runs[0]["per_team_mean_s"] == runs[1]["per_team_mean_s"]
