"""``evaluate.py`` for DQN checkpoints (``agent=dqn``): the saved Q network, fused with the saved H^ by the
run's rule and last weight (the fusion component in evaluation mode), played greedily on fresh episodes."""

from __future__ import annotations

import time
from typing import Any

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torch import nn

from hfrl_torch import keys
from hfrl_torch.agents.dqn import CHOOSABLE, ChosenEstimate, HumanValuesModule, choosable_module
from hfrl_torch.agents.dqn.dqn import CHOSEN_VALUE
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.keepaway import KeepawayConfig, KeepawayEnv
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.experiment.factories import make_env, make_rules
from hfrl_torch.experiment.learners.keepaway_dqn import keeper_scale, play_episodes
from hfrl_torch.experiment.learners.tetris_dqn import play_games
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight
from hfrl_torch.fusion.transform import FusionModule
from hfrl_torch.models.mlp import ActionMLP, AfterstateMLP
from hfrl_torch.models.tile_coding import TileCoding, keepaway_tile_widths

__all__ = ["evaluate_dqn_keepaway", "evaluate_dqn_tetris", "is_dqn"]


def is_dqn(ckpt: dict[str, Any]) -> bool:
    """Whether a checkpoint holds a DQN policy."""
    policy = ckpt.get("policy")
    return isinstance(policy, dict) and policy.get("kind") == "dqn"


class _Values:
    """H^ of every action from a saved model (``HumanValuesModule``'s face)."""

    def __init__(self, fn: Any) -> None:
        self.fn = fn

    @torch.no_grad()
    def values(self, td: Any) -> torch.Tensor:
        return self.fn(td).to(torch.float64)


def _policy(
    q: nn.Module,
    in_key: Any,
    mask_key: Any,
    pre: list[Any],
    payload: dict[str, Any],
    human: Any,
    human_keys: list,
) -> tuple[TensorDictSequential, Fusion]:
    from tensordict.nn import TensorDictModule
    from torchrl.modules import QValueModule

    modules: list[TensorDictModuleBase] = [
        *pre,
        TensorDictModule(q, in_keys=[in_key], out_keys=[keys.ENV_VALUES]),
    ]
    fused = payload.get("fusion")
    if fused is None:
        fusion = Fusion("none", "none", ConstantWeight(0.0))
        modules.append(
            QValueModule(
                action_space="categorical",
                action_value_key=keys.ENV_VALUES,
                action_mask_key=mask_key,
                out_keys=[keys.ACTION, keys.ENV_VALUES, CHOSEN_VALUE],
            )
        )
    else:
        fusion = Fusion(
            fused["scheme"], "none", ConstantWeight(float(fused["weight"])), scaling=fused["scaling"]
        )
        fusion.q_spread.fill_(float(fused["q_spread"]))
        modules += [
            HumanValuesModule(_Values(human), human_keys),
            FusionModule(fusion, "greedy"),
            ChosenEstimate(),
        ]
    return TensorDictSequential(*modules), fusion.eval()


def _load(module: nn.Module, state: Any, what: str) -> nn.Module:
    try:
        module.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError) as e:
        raise CheckpointError(f"the checkpoint's {what} does not load ({e})") from None
    return module.eval()


def evaluate_dqn_tetris(cfg: DictConfig, ckpt: dict[str, Any], label: str) -> dict[str, object]:
    """Play ``games`` fresh games of a Tetris DQN checkpoint (its board; ``domain.max_pieces`` caps them)."""
    p, width, height = ckpt["policy"], int(cfg.domain.width), int(cfg.domain.height)
    q = _load(AfterstateMLP(feature_size(feature_id(p["features"]), width), p["cells"]), p["q"], "Q network")
    human = None
    h = p.get("human")
    if p.get("fusion") is not None and h is not None:
        n = feature_size(feature_id(h["features"]), width)
        if h["kind"] == "mlp":
            model = _load(AfterstateMLP(n, h["cells"], h["scale"]), h["model"], "H^ network")
            human = lambda td: model(placement_deltas(td))  # noqa: E731
        else:
            w = torch.as_tensor(h["weights"], dtype=torch.float64)
            human = lambda td: placement_deltas(td) @ w  # noqa: E731
    policy, fusion = _policy(
        q,
        keys.AFTERSTATE_FEATURES,
        CHOOSABLE,
        [choosable_module()],
        p,
        human,
        [keys.AFTERSTATE_FEATURES, keys.STATE_FEATURES],
    )
    games = int(cfg.games)
    env = make_env(cfg, games, features=p["env_features"])
    env.set_seed(int(cfg.seed))
    t0 = time.perf_counter()
    lines, pieces = play_games(env, policy, fusion)
    elapsed = time.perf_counter() - t0
    s = summarize(lines, floor=0.0)
    rules = make_rules(cfg)
    scheme = "Q alone" if p.get("fusion") is None else f"Q fused with H^ ({p['fusion']['scheme']})"
    return {
        "domain": "tetris",
        "policy": label,
        "features": f"DQN over {p['features']}, {scheme}",
        "rules": rules.describe(),
        "board": f"{width}x{height}",
        "games": games,
        **{k: s[k] for k in ("mean", "sd", "median", "ci95_low", "ci95_high")},
        "max_pieces": int(cfg.domain.max_pieces),
        "capped_games": 0,
        "pieces_per_game": float(pieces.mean()),
        "placements_per_s": float(pieces.sum()) / max(elapsed, 1e-9),
        "seed": int(cfg.seed),
    }


def evaluate_dqn_keepaway(
    cfg: DictConfig, ckpt: dict[str, Any], config: KeepawayConfig, label: str
) -> dict[str, object]:
    """Play ``episodes`` fresh episodes (one per field) of a keepaway DQN checkpoint on its own task."""
    p, s_vars, actions = ckpt["policy"], config.num_state_vars, config.num_actions
    q = _load(ActionMLP(s_vars, actions, p["cells"], keeper_scale(config)), p["q"], "Q network")
    human = None
    h = p.get("human")
    if p.get("fusion") is not None and h is not None:
        if h["kind"] == "mlp":
            model = _load(
                ActionMLP(s_vars, actions, h["cells"], keeper_scale(config)), h["model"], "H^ network"
            )
            human = lambda td: model(td.get(keys.OBSERVATION))  # noqa: E731
        else:
            widths = keepaway_tile_widths(config.keepers, config.takers)
            coder = TileCoding(widths, actions, learners=1, tilings=int(h["tilings"]), size=int(h["size"]))
            coder.weight.copy_(h["weights"])

            def human(td: Any) -> torch.Tensor:
                tiles = coder.tiles(td.get(keys.OBSERVATION).to(torch.float64))
                return coder(torch.zeros(tiles.shape[0], dtype=torch.int64), tiles)

    policy, fusion = _policy(q, keys.OBSERVATION, keys.ACTION_MASK, [], p, human, [keys.OBSERVATION])
    episodes = int(cfg.episodes)
    env = KeepawayEnv(episodes, config, seed=int(cfg.seed), sync="all")
    t0 = time.perf_counter()
    seconds, cause = play_episodes(env, policy, fusion)
    elapsed = time.perf_counter() - t0
    s = summarize(seconds, floor=0.0)
    return {
        "domain": "keepaway",
        "policy": label,
        "preset": config.preset,
        "keepers": config.keepers,
        "takers": config.takers,
        "episodes": episodes,
        "mean_s": s["mean"],
        "sd_s": s["sd"],
        "median_s": s["median"],
        "ci95_low": s["ci95_low"],
        "ci95_high": s["ci95_high"],
        "taken_share": float((cause == 2).double().mean()),
        "out_share": float((cause == 1).double().mean()),
        "cycles_per_s": float(seconds.sum()) * 10.0 / max(elapsed, 1e-9),
        "seed": int(cfg.seed),
    }
