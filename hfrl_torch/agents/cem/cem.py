"""Noisy cross-entropy method for linear Tetris value functions.

Szita & Lőrincz, "Learning Tetris Using the Noisy Cross-Entropy Method",
Neural Computation 2006; the thesis's Section 3.5 (Figure 3.6).

Each iteration samples a population of weight vectors from a diagonal Gaussian,
scores every candidate on the same games (common random numbers), keeps the
elite, and refits the Gaussian to the elite with extra noise added to the
variance so that it does not collapse too early. Every random draw of iteration
t is a function of (seed, t), so a resumed run is identical to an uninterrupted one.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from hfrl_torch.common.seeding import component_seed
from hfrl_torch.common.stats import summarize

# (weights [N, F], game seeds [N]) -> (lines [N], pieces [N], capped [N]: stopped by the piece limit),
# optionally followed by the fitness [N] candidates are ranked by instead of their lines (reward shaping).
Rollout = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]

NOISE_SCHEDULES = ("constant", "decreasing", "none")


@dataclass
class CEMConfig:
    """Settings of the anchors in the spec: 100 candidates, best 10 %, variance 100, noise 4."""

    population: int = 100
    elite_fraction: float = 0.1
    initial_mean: float = 0.0
    initial_variance: float = 100.0
    noise: str = "constant"  # constant: +noise_value; decreasing: +max(noise_start - t / noise_decay, 0)
    noise_value: float = 4.0
    noise_start: float = 5.0
    noise_decay: float = 10.0
    games_per_candidate: int = 1
    eval_games: int = 30

    @property
    def n_elite(self) -> int:
        return max(1, round(self.population * self.elite_fraction))


class CrossEntropyMethod:
    """The noisy CE optimiser over the weights of a linear afterstate value.

    :param num_features: length of the weight vector.
    :param config: population, elite, variance and noise settings.
    :param rollout: plays games of given weight vectors and seeds, returns lines and pieces.
    :param seed: the run's seed.
    :param mean: the initial mean of every dimension (default ``config.initial_mean`` for all).
    :param scale: each dimension's standard deviation relative to the config's (default 1 for all): its
        initial variance and its noise are the config's times ``scale ** 2``. A dimension on another scale
        than the value weights, such as the fusion weight CE searches with them, gets its own this way.
    """

    def __init__(
        self,
        num_features: int,
        config: CEMConfig,
        rollout: Rollout,
        seed: int,
        *,
        mean: torch.Tensor | None = None,
        scale: torch.Tensor | None = None,
    ) -> None:
        self.config = config
        self.rollout = rollout
        self.seed = seed
        self.iteration = 0
        ones = torch.ones(num_features, dtype=torch.float64)
        self.scale = ones if scale is None else torch.as_tensor(scale, dtype=torch.float64).clone()
        if self.scale.shape != (num_features,) or not bool((self.scale > 0).all()):
            raise ValueError(f"CE scale must be {num_features} numbers > 0, got {self.scale.tolist()}")
        self.mean = (
            ones * config.initial_mean if mean is None else torch.as_tensor(mean, dtype=torch.float64).clone()
        )
        if self.mean.shape != (num_features,):
            raise ValueError(f"CE mean must have {num_features} entries, got {tuple(self.mean.shape)}")
        self.variance = config.initial_variance * self.scale**2

    def noise(self, t: int) -> float:
        """Variance added to the elite's at iteration ``t`` (0-based)."""
        c = self.config
        if c.noise == "constant":
            return c.noise_value
        if c.noise == "decreasing":
            return max(c.noise_start - t / c.noise_decay, 0.0)
        return 0.0

    def step(self) -> dict[str, float]:
        """One CE iteration: sample, score on common games, refit; returns metrics of the iteration."""
        c = self.config
        t = self.iteration
        gen = torch.Generator().manual_seed(component_seed(self.seed, "cem_candidates", t))
        std = self.variance.sqrt()
        candidates = self.mean + std * torch.randn(
            c.population, self.mean.numel(), generator=gen, dtype=torch.float64
        )

        game_gen = torch.Generator().manual_seed(component_seed(self.seed, "cem_games", t))
        game_seeds = torch.randint(0, 2**62, (c.games_per_candidate,), generator=game_gen, dtype=torch.int64)
        weights = candidates.repeat_interleave(c.games_per_candidate, dim=0)
        seeds = game_seeds.repeat(c.population)
        lines, pieces, capped, *shaped = self.rollout(weights, seeds)
        fitness = shaped[0].to(torch.float64) if shaped else lines.to(torch.float64)
        scores = fitness.view(c.population, c.games_per_candidate).mean(1)
        lines_per_candidate = lines.to(torch.float64).view(c.population, c.games_per_candidate).mean(1)

        elite = torch.argsort(scores, descending=True, stable=True)[: c.n_elite]
        self.mean = candidates[elite].mean(0)
        self.variance = candidates[elite].var(0, unbiased=False) + self.noise(t) * self.scale**2
        self.iteration += 1

        pop = summarize(lines_per_candidate, floor=0.0)
        metrics = {
            "population/lines_mean": pop["mean"],
            "population/lines_median": pop["median"],
            "population/lines_ci95_low": pop["ci95_low"],
            "population/lines_ci95_high": pop["ci95_high"],
            "population/lines_best": pop["max"],
            "population/elite_lines_mean": float(lines_per_candidate[elite].mean()),
            "population/placements": float(pieces.sum()),
            "population/capped_share": float(capped.double().mean()),
            "cem/noise": self.noise(t),
            "cem/std_mean": float((self.variance.sqrt() / self.scale).mean()),
        }
        if shaped:
            metrics["population/shaping_bonus_mean"] = float((fitness - lines.to(torch.float64)).mean())
        return metrics

    def evaluate_mean(self, games: int | None = None) -> torch.Tensor:
        """Lines per game of the current mean weights on fresh games of this iteration."""
        n = self.config.eval_games if games is None else games
        gen = torch.Generator().manual_seed(component_seed(self.seed, "cem_eval", self.iteration))
        seeds = torch.randint(0, 2**62, (n,), generator=gen, dtype=torch.int64)
        lines, pieces, capped, *_ = self.rollout(self.mean.expand(n, -1), seeds)
        self.last_eval_pieces = int(pieces.sum())
        self.last_eval_capped = int(capped.sum())
        return lines

    def state_dict(self) -> dict[str, object]:
        """Everything needed to continue: the Gaussian and the iteration count."""
        return {"mean": self.mean.clone(), "variance": self.variance.clone(), "iteration": self.iteration}

    def load_state_dict(self, state: dict[str, object]) -> None:
        """Restore :meth:`state_dict`'s output; the weight vector must keep its length."""
        mean = torch.as_tensor(state["mean"], dtype=torch.float64)
        variance = torch.as_tensor(state["variance"], dtype=torch.float64)
        if mean.shape != self.mean.shape or variance.shape != self.variance.shape:
            raise ValueError(
                f"saved CE state has {tuple(mean.shape)} weights; this run needs {tuple(self.mean.shape)}"
            )
        self.mean = mean.clone()
        self.variance = variance.clone()
        self.iteration = int(state["iteration"])
