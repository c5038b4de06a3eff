"""The greedy keepers of a learned keepaway checkpoint (``train.py domain=keepaway agent=sarsa``), for
evaluation: no exploration, no learning.

Field f of the evaluation batch plays for team (learner) f % teams; the keeper with the ball reads its own
weight table (team * keepers + keeper, or the team's with ``share_weights``). Without a trainer the keepers
take argmax Q. With one, they choose by the run's fusion rule on the checkpoint's Q and H^, through the same
fusion component as in training (:class:`~hfrl_torch.fusion.fusion.Fusion`, in evaluation mode), with the
weight w each team had when the checkpoint was written:

* ``none``, ``reward_shaping``: argmax Q (shaping acts on the reward Sarsa learned from, not the choice);
* ``human_only``: argmax H^;
* ``linear``, ``action_biasing``, ``annealed``, ``exponential``: argmax of the fused values, on Q and H^ put
  on one scale as the run did (``spread``: H^ times the team's Q spread when the checkpoint was written,
  raw values for the exponential rule;
  ``decision``: both rescaled to [0, 1] over the available actions; ``none``: raw);
* ``control_sharing``: argmax H^ where w >= 0.5, else argmax Q. Training follows H^ with probability
  min(w, 1); evaluation takes that draw's more likely outcome, so a policy plays the same way every time.

Ties of the greedy choice are broken uniformly at random from the generator given, drawn for every row on
every call (the random stream does not depend on the choices), as ``SarsaLambda.select`` does.
"""

from __future__ import annotations

from typing import Any

import torch
from tensordict import TensorDict
from torch import Tensor

from hfrl_torch import keys
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.envs.keepaway import KeeperChooser
from hfrl_torch.fusion.fusion import SCALINGS, Fusion
from hfrl_torch.fusion.schedules import ConstantWeight
from hfrl_torch.fusion.schemes import FUSIONS
from hfrl_torch.models.tile_coding import TileCoding


def greedy_with_random_ties(values: Tensor, mask: Tensor, generator: torch.Generator) -> Tensor:
    """The best available action [M] of ``values`` [M, A] under ``mask`` [M, A], ties broken uniformly."""
    noise = torch.rand(values.shape, generator=generator, device=generator.device).to(values.device)
    best = values.masked_fill(~mask, -torch.inf).amax(1, keepdim=True)
    return torch.where(mask & (values == best), noise, -1.0).argmax(1)


def _coder(policy: dict[str, Any], weight: Tensor, device: torch.device) -> TileCoding:
    coder = TileCoding(
        policy["tile_widths"],
        num_actions=int(policy["num_actions"]),
        learners=weight.shape[0],
        tilings=int(policy["tilings"]),
        size=int(policy["size"]),
        dtype=weight.dtype,
        device=device,
    )
    if tuple(weight.shape) != (weight.shape[0], coder.size):
        raise ValueError(f"weights of shape {tuple(weight.shape)} for a table of {coder.size}")
    coder.weight.copy_(weight)
    return coder


def load_keeper_policy(
    checkpoint: dict[str, Any],
    device: str | torch.device = "cpu",
    generator: torch.Generator | None = None,
) -> tuple[KeeperChooser, dict[str, Any]]:
    """The greedy chooser ``choose(obs [B, F], mask [B, A], holder [B]) -> actions [B]`` of a keepaway Sarsa
    checkpoint (as :func:`load_checkpoint` returns it), and what it plays: ``teams``, ``keepers``,
    ``takers``, ``scheme`` (the fusion rule; "none" without a trainer), ``weight`` (w per team or None)
    and ``share_weights``.

    :param generator: source of the tie-breaking draws (on ``device``); None: one seeded with 0.
    :raises CheckpointError: one line, when the checkpoint is not a readable tile-coded Sarsa policy.
    """
    device = torch.device(device)
    if generator is None:
        generator = torch.Generator(device=device).manual_seed(0)
    where = checkpoint.get("path", "the checkpoint")
    try:
        policy = checkpoint["policy"]
        if policy.get("kind") != "tile_sarsa":
            raise ValueError(f"policy kind {policy.get('kind')!r}, expected 'tile_sarsa'")
        keepers = int(checkpoint["domain_config"]["keepers"])
        takers = int(checkpoint["domain_config"]["takers"])
        teams, share = int(policy["teams"]), bool(policy["share_weights"])
        features = 4 * keepers + 2 * takers - 3
        if int(policy["num_actions"]) != keepers or len(policy["tile_widths"]) != features:
            raise ValueError(
                f"{policy['num_actions']} actions over {len(policy['tile_widths'])} state variables "
                f"for {keepers}v{takers}"
            )
        weight = checkpoint["state"]["agent"]["weight"]
        if weight.shape[0] != (teams if share else teams * keepers):
            raise ValueError(f"{weight.shape[0]} weight tables for {teams} teams of {keepers} keepers")
        coder = _coder(policy, weight, device)
        human = policy.get("human")
        scheme, w, per_keeper, model, fusion = "none", None, False, None, None
        if human is not None:
            scheme, scaling = str(human["scheme"]), str(human["scaling"])
            if scaling not in SCALINGS:
                raise ValueError(f"scaling {scaling!r}")
            spread = torch.as_tensor(human["q_spread"], dtype=torch.float64)
            if spread.shape != (teams,):
                raise ValueError(f"{spread.numel()} Q spreads for {teams} teams")
            if scheme not in FUSIONS:
                raise ValueError(f"fusion scheme {scheme!r}")
            per_keeper = human["model"] == "keeper"
            w = torch.as_tensor(human["weight"], dtype=torch.float64)
            if w.shape != (teams,):
                raise ValueError(f"{w.numel()} fusion weights for {teams} teams")
            model = _coder(policy, checkpoint["state"]["human"]["human_weight"], device)
            if model.learners != (teams * keepers if per_keeper else teams):
                raise ValueError(f"{model.learners} H^ models of kind {human['model']!r} for {teams} teams")
            fusion = Fusion.from_option(scheme, ConstantWeight(w.tolist()), scaling=scaling).eval()
            fusion.q_spread = spread.clone()
    except (KeyError, TypeError, ValueError, AttributeError, RuntimeError) as e:
        raise CheckpointError(f"checkpoint {where!r} holds no playable keepaway policy ({e})") from None

    def choose(obs: Tensor, mask: Tensor, holder: Tensor) -> Tensor:
        team = torch.arange(obs.shape[0], device=device) % teams
        holder = holder.to(device)
        mask = mask.to(device=device, dtype=torch.bool)
        tiles = coder.tiles(obs.to(device=device, dtype=torch.float32))
        q = coder(team if share else team * keepers + holder, tiles)
        values = q
        if fusion is not None:
            h = model(team * keepers + holder if per_keeper else team, tiles).to(torch.float64)
            decisions = TensorDict(
                {keys.ENV_VALUES: q, keys.HUMAN_VALUES: h, keys.ACTION_MASK: mask, keys.LEARNER: team.cpu()},
                batch_size=[obs.shape[0]],
            )
            values = fusion.fuse(decisions).get(keys.FUSED_VALUES)
        return greedy_with_random_ties(values, mask, generator).to(obs.device)

    info = {
        "teams": teams,
        "keepers": keepers,
        "takers": takers,
        "scheme": scheme,
        "weight": None if w is None else w.tolist(),
        "share_weights": share,
    }
    return choose, info
