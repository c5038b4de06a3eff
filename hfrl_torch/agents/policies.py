"""A saved policy: one schema every learner writes, one loader table, one dispatch.

**Schema.** A checkpoint's ``"policy"`` entry is a dict ``{"kind": <kind>, ...its state}`` that a learner
writes with :func:`export_policy`; ``kind`` names the loader in :data:`POLICY_LOADERS` that plays it:

* ``linear``: a linear afterstate value over a Tetris feature set (``features``, ``weights``; CE, TAMER,
  Q-learning and policy-gradient runs), played greedily;
* ``fused``: CE's value fused with the trainer's H^ by the run's rule at its last weight (``scheme``,
  ``weight``, ``normalise``, ``human_features``, ``human_weights`` besides the linear keys);
* ``tetris_dqn`` / ``keepaway_dqn`` / ``gym_dqn``: the saved Q network (and, with a trainer, H^ and the
  fusion rule); ``gym_dqn`` also keeps the ``task`` it learned, which ``evaluate.py`` plays it on;
* ``gym_tamer``: TAMER's H^ alone (Deep TAMER's network on the observation), played greedily, with its
  ``task``;
* ``gym_ppo``: PPO's policy network (``actor``, one logit per action), played greedily as ``gym_dqn`` plays
  Q (argmax of the logits, fused with H^ where the run had a trainer), on its ``task``;
* ``tile_sarsa``: the keepaway Sarsa keepers' tile coding (and H^ by the run's fusion rule). Its weight
  tables stay where the run's state keeps them (``state -> agent -> weight``, ``state -> human ->
  human_weight``), so a checkpoint holds them once.

**Loading.** :func:`load_policy` takes a checkpoint as :func:`~hfrl_torch.common.checkpoint.load_checkpoint`
returns it and gives ``(module, info)``: ``module`` is a TorchRL policy (a ``TensorDictModule`` or
``TensorDictSequential``) that reads the domain's observation keys (Tetris: ``afterstate_features``,
``state_features``, ``action_mask``, ``afterstate_terminal``; keepaway: ``observation``, ``action_mask``,
``keeper``) and writes ``"action"``, greedily, the fusion component in evaluation mode. ``info`` says what it
plays (``kind``, ``fusion``, ``describe``; Tetris: ``env_features``, the feature set the env must compute,
and ``board_width``; keepaway: ``teams`` and the fusion ``scheme``/``weight``; gym: the ``task`` and its
``observation_size`` and ``actions``), and, where the domain has a
faster batched player for the same policy, the policy in that player's form: ``afterstate`` (Tetris: the
linear afterstate weights the compiled rollout plays, with the fused H^ part) or ``chooser`` (keepaway: the
``choose(obs, mask, holder)`` function the batched simulator calls). ``evaluate.py`` plays that form where a
policy has one (the numbers it always printed) and the module on the TorchRL env otherwise.

Checkpoints saved before this schema still load: :func:`policy_kind` maps their kinds in one place.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
from omegaconf import OmegaConf
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import Tensor, nn
from torchrl.modules import QValueModule

from hfrl_torch import keys
from hfrl_torch.agents.dqn import CHOOSABLE, ChosenEstimate, HumanValuesModule, choosable_module
from hfrl_torch.agents.dqn.dqn import CHOSEN_VALUE
from hfrl_torch.agents.sarsa.policy import load_keeper_policy
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.common.frames import image_shape
from hfrl_torch.envs.keepaway import KeepawayConfig, KeeperChooser
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.fusion.fusion import Fusion
from hfrl_torch.fusion.schedules import ConstantWeight
from hfrl_torch.fusion.transform import FusionModule
from hfrl_torch.models.cnn import ActionCNN
from hfrl_torch.models.linear import greedy_placement
from hfrl_torch.models.mlp import ActionMLP, AfterstateMLP, keeper_scale
from hfrl_torch.models.tile_coding import TileCoding, keepaway_tile_widths

__all__ = ["POLICY_LOADERS", "export_policy", "load_policy", "policy_kind", "register_policy_loader"]

Loaded = tuple[TensorDictModuleBase, dict[str, Any]]
PolicyLoader = Callable[[dict[str, Any], torch.device, torch.Generator], Loaded]
"""``loader(checkpoint, device, generator) -> (module, info)``; raises ``ValueError``, ``KeyError``,
``TypeError`` or ``RuntimeError`` on a policy it cannot read (``load_policy`` makes that one line)."""

POLICY_LOADERS: dict[str, PolicyLoader] = {}


def register_policy_loader(kind: str) -> Callable[[PolicyLoader], PolicyLoader]:
    """Make ``kind`` loadable by the decorated loader (a learner from outside the package adds its own)."""

    def add(loader: PolicyLoader) -> PolicyLoader:
        if kind in POLICY_LOADERS and POLICY_LOADERS[kind] is not loader:
            raise ValueError(f"policy kind {kind!r} has a loader already")
        POLICY_LOADERS[kind] = loader
        return loader

    return add


def export_policy(kind: str, **state: Any) -> dict[str, Any]:
    """The ``"policy"`` entry of a checkpoint: ``{"kind": kind, **state}``; every learner writes it here.

    :raises ValueError: ``kind`` has no loader (a policy nothing could play is not written).
    """
    if kind not in POLICY_LOADERS:
        raise ValueError(f"policy kind {kind!r} has no loader; allowed: {', '.join(sorted(POLICY_LOADERS))}")
    return {"kind": kind, **state}


def policy_kind(checkpoint: dict[str, Any]) -> str:
    """The loader kind of a checkpoint's policy, checkpoints saved before this schema included.

    Legacy forms, mapped here only: ``"dqn"`` (both DQN learners wrote it, before a kind named its loader)
    is ``<domain>_dqn``; a Tetris policy with ``features`` and ``weights`` but no ``kind`` (the earliest
    checkpoints, which ``evaluate.py`` always played as linear) is ``linear``.
    """
    policy = checkpoint["policy"]
    if not isinstance(policy, dict):
        raise CheckpointError(
            f"checkpoint {checkpoint.get('path', '')!r} holds a policy of type {type(policy).__name__}, "
            "not a dict"
        )
    kind = policy.get("kind")
    domain = checkpoint.get("domain")
    if kind == "dqn" and domain in ("tetris", "keepaway", "gym"):
        return f"{domain}_dqn"
    if kind is None and domain == "tetris" and "features" in policy and "weights" in policy:
        return "linear"
    return kind


def load_policy(
    checkpoint: dict[str, Any],
    device: str | torch.device = "cpu",
    generator: torch.Generator | None = None,
) -> Loaded:
    """The policy a checkpoint saved, as ``(module, info)`` (the module docstring says what each holds).

    :param checkpoint: as :func:`~hfrl_torch.common.checkpoint.load_checkpoint` returns it.
    :param generator: the random draws the policy makes (keepaway Sarsa's tie breaks); None: seeded with 0.
    :raises CheckpointError: one line, on an unknown kind (naming it and the allowed ones) or a policy its
        loader cannot read.
    """
    device = torch.device(device)
    if generator is None:
        generator = torch.Generator(device=device).manual_seed(0)
    where = checkpoint.get("path", "the checkpoint")
    kind = policy_kind(checkpoint)
    if not isinstance(kind, str) or kind not in POLICY_LOADERS:
        raise CheckpointError(
            f"checkpoint {where!r} holds a policy of kind {kind!r}; "
            f"allowed: {', '.join(sorted(POLICY_LOADERS))}"
        )
    try:
        module, info = POLICY_LOADERS[kind](checkpoint, device, generator)
    except CheckpointError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as e:
        raise CheckpointError(
            f"checkpoint {where!r} holds no playable {kind} policy ({_one_line(e)})"
        ) from None
    return module, {"kind": kind, **info}


def _one_line(e: BaseException) -> str:
    """An exception's words on one line, at most 200 characters (torch's load errors run over several)."""
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 200 else text[:197] + "..."


# ---------------------------------------------------------------------------------------------- Tetris


def _board_width(checkpoint: dict[str, Any]) -> int:
    return int(OmegaConf.create(checkpoint["config"]).domain.width)


def _greedy_afterstate(values: Tensor, mask: Tensor, terminal: Tensor) -> Tensor:
    return greedy_placement(values, mask.to(torch.bool), terminal)


class _LinearValues(nn.Module):
    """Values [B, A] of every placement: the first ``len(weights)`` afterstate features times the weights."""

    def __init__(self, weights: Tensor) -> None:
        super().__init__()
        self.register_buffer("weights", weights.to(torch.float64))

    def forward(self, afterstate: Tensor) -> Tensor:
        return afterstate[..., : self.weights.numel()].to(torch.float64) @ self.weights


def _afterstate_form(policy: dict[str, Any]) -> dict[str, Any]:
    features = str(policy["features"])
    weights = torch.as_tensor(policy["weights"], dtype=torch.float64)
    if weights.ndim != 1:
        raise ValueError(f"weights of shape {tuple(weights.shape)}, not one vector")
    feature_id(features)
    return {"features": features, "weights": weights, "fused": None}


@register_policy_loader("linear")
def _load_linear(checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator) -> Loaded:
    width = _board_width(checkpoint)
    form = _afterstate_form(checkpoint["policy"])
    module = TensorDictSequential(
        TensorDictModule(_LinearValues(form["weights"]), [keys.AFTERSTATE_FEATURES], [keys.ENV_VALUES]),
        TensorDictModule(
            _greedy_afterstate,
            [keys.ENV_VALUES, keys.ACTION_MASK, keys.AFTERSTATE_TERMINAL],
            [keys.ACTION],
        ),
    ).to(device)
    info = {
        "fusion": None,
        "describe": form["features"],
        "env_features": form["features"],
        "board_width": width,
        "afterstate": form,
    }
    return module, info


class _Values:
    """H^ of every action from a saved model (``HumanValuesModule``'s face)."""

    def __init__(self, fn: Callable[[TensorDictBase], Tensor]) -> None:
        self.fn = fn

    @torch.no_grad()
    def values(self, td: TensorDictBase) -> Tensor:
        return self.fn(td).to(torch.float64)


def _linear_human(weights: Tensor) -> _Values:
    return _Values(lambda td: placement_deltas(td) @ weights)


@register_policy_loader("fused")
def _load_fused(checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator) -> Loaded:
    p, width = checkpoint["policy"], _board_width(checkpoint)
    form = _afterstate_form(p)
    weight = float(p["weight"])
    fusion = Fusion(
        str(p["scheme"]), "none", ConstantWeight(weight), scaling="decision" if p["normalise"] else "none"
    ).eval()
    human_features = str(p["human_features"])
    human_weights = torch.as_tensor(p["human_weights"], dtype=torch.float64)
    if human_weights.numel() != feature_size(feature_id(human_features), width):
        raise ValueError(
            f"{human_weights.numel()} H^ weights over {human_features!r} on a board {width} wide"
        )
    form["fused"] = {
        "scheme": str(p["scheme"]),
        "weight": weight,
        "normalise": bool(p["normalise"]),
        "human_features": human_features,
        "human_weights": human_weights,
    }
    module = TensorDictSequential(
        TensorDictModule(_LinearValues(form["weights"]), [keys.AFTERSTATE_FEATURES], [keys.ENV_VALUES]),
        HumanValuesModule(_linear_human(human_weights), [keys.AFTERSTATE_FEATURES, keys.STATE_FEATURES]),
        FusionModule(fusion, "greedy"),
    ).to(device)
    info = {
        "fusion": fusion,
        "describe": (
            f"{form['features']} fused with H^ over {human_features} "
            f"({form['fused']['scheme']}, w={weight:.3g})"
        ),
        "env_features": human_features,  # the CE value's set is its prefix (bt of knox) or the same
        "board_width": width,
        "afterstate": form,
    }
    return module, info


def _load_state(module: nn.Module, state: Any, what: str) -> nn.Module:
    try:
        module.load_state_dict(state)
    except (RuntimeError, KeyError, TypeError) as e:
        raise ValueError(f"its {what} does not load: {_one_line(e)}") from None
    return module.eval()


def _dqn_policy(
    q: nn.Module,
    in_key: Any,
    mask_key: Any,
    pre: list[TensorDictModuleBase],
    payload: dict[str, Any],
    human: _Values | None,
    human_keys: list[Any],
) -> tuple[TensorDictSequential, Fusion]:
    """Q (and, with a trainer's H^, the fusion component at its saved weight) to a greedy action."""
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
        if human is None:
            raise ValueError("a fused DQN policy without its H^")
        fusion = Fusion(
            fused["scheme"], "none", ConstantWeight(float(fused["weight"])), scaling=fused["scaling"]
        )
        fusion.q_spread.fill_(float(fused["q_spread"]))
        modules += [HumanValuesModule(human, human_keys), FusionModule(fusion, "greedy"), ChosenEstimate()]
    return TensorDictSequential(*modules), fusion.eval()


def _fusion_words(p: dict[str, Any]) -> str:
    return "Q alone" if p.get("fusion") is None else f"Q fused with H^ ({p['fusion']['scheme']})"


@register_policy_loader("tetris_dqn")
def _load_tetris_dqn(checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator) -> Loaded:
    p, width = checkpoint["policy"], _board_width(checkpoint)
    q = _load_state(
        AfterstateMLP(feature_size(feature_id(p["features"]), width), p["cells"]), p["q"], "Q network"
    )
    human = None
    h = p.get("human")
    if p.get("fusion") is not None and h is not None:
        n = feature_size(feature_id(h["features"]), width)
        if h["kind"] == "mlp":
            model = _load_state(AfterstateMLP(n, h["cells"], h["scale"]), h["model"], "H^ network")
            human = _Values(lambda td: model(placement_deltas(td)))
        else:
            human = _linear_human(torch.as_tensor(h["weights"], dtype=torch.float64))
    module, fusion = _dqn_policy(
        q,
        keys.AFTERSTATE_FEATURES,
        CHOOSABLE,
        [choosable_module()],
        p,
        human,
        [keys.AFTERSTATE_FEATURES, keys.STATE_FEATURES],
    )
    info = {
        "fusion": fusion,
        "describe": f"DQN over {p['features']}, {_fusion_words(p)}",
        "env_features": str(p["env_features"]),
        "board_width": width,
        "afterstate": None,
    }
    return module.to(device), info


def _gym_policy(
    checkpoint: dict[str, Any], device: torch.device, key: str, what: str, describe: str
) -> Loaded:
    """A network of one value per action on the observation (``key`` in the policy), played greedily
    (fused with the saved H^ where the run had a trainer), and the ``task`` it learned."""
    p = checkpoint["policy"]
    net = _load_state(_gym_net(p, p["cells"]), p[key], what)
    human = None
    h = p.get("human")
    if p.get("fusion") is not None and h is not None:
        model = _load_state(_gym_net(p, h["cells"]), h["model"], "H^ network")
        human = _Values(lambda td: model(td.get(keys.OBSERVATION)))
    module, fusion = _dqn_policy(net, keys.OBSERVATION, None, [], p, human, [keys.OBSERVATION])
    info = {"fusion": fusion, "describe": describe, **_gym_task(p)}
    return module.to(device), info


def _gym_net(p: dict[str, Any], cells: list[int]) -> ActionMLP | ActionCNN:
    """The network shape a gym policy saved: DQN's CNN on a frame (``observation_shape`` [H, W, C]), else
    an MLP on the observation vector (policies saved before frames were allowed name no shape)."""
    frame = image_shape(p.get("observation_shape") or ())
    if frame is not None:
        return ActionCNN(frame, int(p["actions"]), cells)
    return ActionMLP(int(p["observation_size"]), int(p["actions"]), cells, p["scale"])


def _gym_task(p: dict[str, Any]) -> dict[str, Any]:
    """What a gym policy says of the task it learned (``evaluate.py`` plays it there; a reference is checked
    against it)."""
    return {
        "task": dict(p["task"]),
        "observation_size": int(p["observation_size"]),
        "actions": int(p["actions"]),
    }


@register_policy_loader("gym_tamer")
def _load_gym_tamer(checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator) -> Loaded:
    p = checkpoint["policy"]
    model = _load_state(_gym_net(p, p["cells"]), p["model"], "H^ network")
    fusion = Fusion("human_only", "none", ConstantWeight(0.0)).eval()
    module = TensorDictSequential(
        TensorDictModule(model, in_keys=[keys.OBSERVATION], out_keys=[keys.HUMAN_VALUES]),
        FusionModule(fusion, "greedy"),
    )
    info = {"fusion": fusion, "describe": "TAMER, greedy on H^", **_gym_task(p)}
    return module.to(device), info


@register_policy_loader("gym_dqn")
def _load_gym_dqn(checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator) -> Loaded:
    return _gym_policy(checkpoint, device, "q", "Q network", f"DQN, {_fusion_words(checkpoint['policy'])}")


@register_policy_loader("gym_ppo")
def _load_gym_ppo(checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator) -> Loaded:
    """PPO's policy network played greedily: argmax of its logits (fused with H^ as ``gym_dqn`` fuses Q)."""
    fused = checkpoint["policy"].get("fusion")
    words = "logits alone" if fused is None else f"logits fused with H^ ({fused['scheme']})"
    return _gym_policy(checkpoint, device, "actor", "policy network", f"PPO (greedy), {words}")


# -------------------------------------------------------------------------------------------- keepaway


def _keepaway_config(checkpoint: dict[str, Any]) -> KeepawayConfig:
    return KeepawayConfig(**checkpoint["domain_config"])


@register_policy_loader("keepaway_dqn")
def _load_keepaway_dqn(
    checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator
) -> Loaded:
    p, config = checkpoint["policy"], _keepaway_config(checkpoint)
    s_vars, actions = config.num_state_vars, config.num_actions
    q = _load_state(ActionMLP(s_vars, actions, p["cells"], keeper_scale(config)), p["q"], "Q network")
    human = None
    h = p.get("human")
    if p.get("fusion") is not None and h is not None:
        if h["kind"] == "mlp":
            model = _load_state(
                ActionMLP(s_vars, actions, h["cells"], keeper_scale(config)), h["model"], "H^ network"
            )
            human = _Values(lambda td: model(td.get(keys.OBSERVATION)))
        else:
            widths = keepaway_tile_widths(config.keepers, config.takers)
            coder = TileCoding(widths, actions, learners=1, tilings=int(h["tilings"]), size=int(h["size"]))
            coder.weight.copy_(h["weights"])

            def tile_values(td: TensorDictBase) -> Tensor:
                tiles = coder.tiles(td.get(keys.OBSERVATION).to(torch.float64))
                return coder(torch.zeros(tiles.shape[0], dtype=torch.int64), tiles)

            human = _Values(tile_values)
    module, fusion = _dqn_policy(q, keys.OBSERVATION, keys.ACTION_MASK, [], p, human, [keys.OBSERVATION])
    info = {
        "fusion": fusion,
        "describe": f"DQN, {_fusion_words(p)}",
        "teams": 1,
        "scheme": "none" if p.get("fusion") is None else str(p["fusion"]["scheme"]),
        "weight": None if p.get("fusion") is None else [float(p["fusion"]["weight"])],
        "chooser": None,
    }
    return module.to(device), info


class _Chooser(nn.Module):
    """A keeper chooser ``choose(obs, mask, holder)`` as a module over the keepaway observation keys."""

    def __init__(self, choose: KeeperChooser) -> None:
        super().__init__()
        self.choose = choose

    def forward(self, obs: Tensor, mask: Tensor, keeper: Tensor) -> Tensor:
        return self.choose(obs, mask, keeper.reshape(-1).to(torch.int64))


@register_policy_loader("tile_sarsa")
def _load_tile_sarsa(checkpoint: dict[str, Any], device: torch.device, generator: torch.Generator) -> Loaded:
    choose, played = load_keeper_policy(checkpoint, device, generator)
    module = TensorDictModule(
        _Chooser(choose), in_keys=[keys.OBSERVATION, keys.ACTION_MASK, keys.KEEPER], out_keys=[keys.ACTION]
    )
    scheme = played["scheme"]
    info = {
        **played,
        "fusion": None,
        "describe": "Sarsa keepers" + ("" if scheme == "none" else f", fused with H^ ({scheme})"),
        "chooser": choose,
    }
    return module, info
