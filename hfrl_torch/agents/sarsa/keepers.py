"""Sarsa keepers for a batch of keepaway fields: the reference's tile coding, a weight table per keeper."""

from __future__ import annotations

import torch

from hfrl_torch.agents.sarsa.sarsa import SarsaLambda
from hfrl_torch.agents.sarsa.sarsa_numba import SarsaLambdaNumba
from hfrl_torch.envs.keepaway.params import KeepawayConfig
from hfrl_torch.models.tile_coding import TileCoding, keepaway_tile_widths

LEARNER_KERNELS = ("auto", "numba", "torch")


def resolve_learner_kernels(kernels: str, device: str | torch.device) -> str:
    """``"numba"`` or ``"torch"``: how the Sarsa learner decides (``"auto"``: numba on the CPU, torch
    elsewhere). Both choose the same actions; weights agree within float32 rounding."""
    if kernels not in LEARNER_KERNELS:
        raise ValueError(f"kernels={kernels!r} is invalid; allowed: {', '.join(LEARNER_KERNELS)}")
    on_cpu = torch.device(device).type == "cpu"
    if kernels == "auto":
        return "numba" if on_cpu else "torch"
    if kernels == "numba" and not on_cpu:
        raise ValueError(f"kernels='numba' runs on the CPU only, not device={device}; use 'auto' or 'torch'")
    return kernels


def sarsa_keepers(
    config: KeepawayConfig,
    learners: int,
    *,
    fields_per_learner: int = 1,
    alpha: float = 0.125,
    epsilon: float = 0.01,
    lambda_: float = 0.0,
    gamma: float = 1.0,
    tilings: int = 32,
    size: int = 2**20,
    min_trace: float = 0.01,
    max_traces: int | None = None,
    share_weights: bool = False,
    seed: int = 0,
    device: str | torch.device = "cpu",
    kernels: str = "torch",
) -> SarsaLambda:
    """Sarsa(lambda) keepers for ``learners`` teams of ``fields_per_learner`` fields each, tile-coded with
    the reference's widths. Agent rows (pending action, traces) are per field and keeper, f * keepers +
    k; weight tables are per team and keeper, (f // fields_per_learner) * keepers + k, or per team with
    ``share_weights`` (the keepers of a team share it, the reference's "hive mind"). ``kernels``
    (:data:`LEARNER_KERNELS`) picks the torch learner or its compiled twin."""
    n = config.keepers
    slots = torch.arange(learners * fields_per_learner * n)
    team = slots // n // fields_per_learner
    coder = TileCoding(
        keepaway_tile_widths(n, config.takers),
        num_actions=config.num_actions,
        learners=learners if share_weights else learners * n,
        tilings=tilings,
        size=size,
        device=device,
    )
    tables = team if share_weights else team * n + slots % n
    learner = SarsaLambdaNumba if resolve_learner_kernels(kernels, device) == "numba" else SarsaLambda
    return learner(coder, alpha, epsilon, lambda_, gamma, min_trace, max_traces, seed=seed, tables=tables)
