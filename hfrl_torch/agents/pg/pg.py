"""Policy gradient for Tetris placements: a softmax over afterstate values, REINFORCE or natural gradient.

Williams (1992), "Simple statistical gradient-following algorithms" (REINFORCE with a baseline); Kakade
(2001), "A Natural Policy Gradient" (Tetris was its test domain); the thesis's section 3.4 (Figure 3.5:
about 6,000 lines per game after 10,000 games on 10 x 20, with the Libpg library).
"""

from __future__ import annotations

import torch
from torch import nn

from hfrl_torch.agents.qlearning.qlearning import allowed_placements


def score_and_fisher(
    features: torch.Tensor,
    allowed: torch.Tensor,
    action: torch.Tensor,
    weight: torch.Tensor,
    temperature: float,
    fisher: bool = True,
    values: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The score grad_theta log pi(a | s) ``[L, F]`` of the placements taken and (with ``fisher``) the
    Fisher matrix of each state, E_a~pi[score score^T] ``[L, F, F]``, under
    pi(a | s) = softmax over the allowed placements of theta . f(s'_a) / T.

    With fbar = E_a~pi f(s'_a): score = (f(s'_a) - fbar) / T and Fisher = Cov_pi(f(s'_a)) / T^2 (the exact
    expectation over the placements, Kakade's F_s(theta), not the outer product of the one sampled).
    ``values`` ``[L, A]`` replaces theta . f in the logits (e.g. theta . f + w H^, fused with the person's
    model by ``hfrl_torch.fusion``); what it adds does not depend on theta, so the score keeps its form.
    """
    f = features.to(torch.float64)
    if values is None:
        values = torch.einsum("laf,lf->la", f, weight)
    logits = values.to(torch.float64) / temperature
    p = logits.masked_fill(~allowed, -torch.inf).softmax(-1)
    centred = (f - (p.unsqueeze(-1) * f).sum(1, keepdim=True)) / temperature
    score = centred[torch.arange(f.shape[0]), action]
    if not fisher:
        return score, None
    return score, torch.einsum("la,laf,lag->lfg", p, centred, centred)


def natural_direction(gradient: torch.Tensor, fisher: torch.Tensor, damping: float) -> torch.Tensor:
    """(F + damping I)^-1 g per learner: ``gradient`` ``[L, F]``, ``fisher`` ``[L, F, F]``."""
    eye = torch.eye(fisher.shape[-1], dtype=fisher.dtype)
    return torch.linalg.solve(fisher + damping * eye, gradient.unsqueeze(-1)).squeeze(-1)


class PolicyGradient(nn.Module):
    """Episodic REINFORCE with a baseline, or its natural-gradient variant, one learner per board.

    The policy is pi(a | s) = softmax over the allowed placements (valid, and not game-ending unless every
    placement ends the game) of theta . f(s'_a) / T, with f(s'_a) the features of the afterstate of a:
    greedy on theta it is the linear afterstate policy a checkpoint stores. Each game e of a learner gives
    its return G_e (the lines it cleared) and the summed score z_e = sum_t grad log pi(a_t | s_t). After
    ``games_per_update`` games (K) the learner ascends

        g = 1/K sum_e (G_e - b_e) z_e,          theta <- theta + lr * g              (vanilla)
        F = 1/K sum_e sum_t F_{s_t},            theta <- theta + lr * (F + d I)^-1 g  (natural)

    where b_e, the baseline, is the exponentially weighted mean of the learner's returns before game e
    (weights ``baseline_decay``^age; 0 before the first game; the plain running mean with decay 1), and
    F_s = E_a~pi[score score^T] is the Fisher matrix of state s, summed over a game (the Fisher matrix of
    the game's trajectory distribution) and damped by d (Kakade 2001; Peters & Schaal's episodic form).
    Placements are sampled with the module's own seeded generator, so a run is a function of its seeds.
    Games that have not yet filled a batch of K wait for the next step (none comes after the last game).

    :param num_features: F, the size of the env's feature set.
    :param learners: L, independent learners (``weight`` ``[L, F]``, float64, starting at 0: uniform play).
    :param lr: the step size.
    :param temperature: T, dividing the logits.
    :param natural: precondition with the damped Fisher matrix.
    :param damping: d, added to the Fisher matrix's diagonal.
    :param games_per_update: K, games per gradient step.
    :param baseline_decay: weight per game of age of past returns in the baseline, in 0..1.
    :param seed: seeds the sampling generator.
    """

    def __init__(
        self,
        num_features: int,
        learners: int,
        lr: float,
        temperature: float = 1.0,
        natural: bool = False,
        damping: float = 1.0,
        games_per_update: int = 1,
        baseline_decay: float = 0.9,
        seed: int = 0,
    ) -> None:
        super().__init__()
        if num_features < 1 or learners < 1 or games_per_update < 1:
            raise ValueError(
                "need num_features, learners and games_per_update >= 1, got "
                f"{num_features}, {learners} and {games_per_update}"
            )
        if not lr > 0 or not temperature > 0 or not damping >= 0 or not 0 <= baseline_decay <= 1:
            raise ValueError(
                f"need lr > 0, temperature > 0, damping >= 0 and baseline_decay in 0..1, got {lr!r}, "
                f"{temperature!r}, {damping!r} and {baseline_decay!r}"
            )
        if natural and damping == 0:
            raise ValueError("the natural gradient needs damping > 0 (the Fisher matrix may be singular)")
        self.weight = nn.Parameter(
            torch.zeros(learners, num_features, dtype=torch.float64), requires_grad=False
        )
        self.lr, self.temperature = float(lr), float(temperature)
        self.natural, self.damping = bool(natural), float(damping)
        self.games_per_update, self.baseline_decay = int(games_per_update), float(baseline_decay)
        self.generator = torch.Generator().manual_seed(int(seed))
        f = num_features
        self.game_score = torch.zeros(learners, f, dtype=torch.float64)  # z of the game in progress
        self.game_fisher = torch.zeros(learners, f, f, dtype=torch.float64)  # sum_t F_{s_t} of that game
        self.gradient_sum = torch.zeros(learners, f, dtype=torch.float64)  # sum_e (G_e - b_e) z_e
        self.fisher_sum = torch.zeros(learners, f, f, dtype=torch.float64)
        self.games_in_update = torch.zeros(learners, dtype=torch.int64)
        self.baseline_num = torch.zeros(learners, dtype=torch.float64)  # sum of decay^age * G
        self.baseline_den = torch.zeros(learners, dtype=torch.float64)  # sum of decay^age
        self.updates = torch.zeros(learners, dtype=torch.int64)

    @property
    def learners(self) -> int:
        return self.weight.shape[0]

    @property
    def baseline(self) -> torch.Tensor:
        """b ``[L]``: the exponentially weighted mean of each learner's past returns (0 before any)."""
        return torch.where(
            self.baseline_den > 0, self.baseline_num / self.baseline_den.clamp(min=1e-300), 0.0
        )

    def values(self, features: torch.Tensor) -> torch.Tensor:
        """theta . f(s'_a) ``[L, A]``: the logits before the temperature (R, for fusion)."""
        return torch.einsum("laf,lf->la", features.to(torch.float64), self.weight)

    def forward(
        self,
        features: torch.Tensor,
        mask: torch.Tensor,
        terminal: torch.Tensor,
        values: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """log pi(a | s) ``[L, A]`` of every placement (-inf where not allowed); ``values`` ``[L, A]``
        replaces theta . f before dividing by T (fused with H^: pi ~ exp((theta . f + w H^) / T))."""
        logits = (self.values(features) if values is None else values.to(torch.float64)) / self.temperature
        return logits.masked_fill(~allowed_placements(mask, terminal), -torch.inf).log_softmax(-1)

    @torch.no_grad()
    def act(
        self,
        features: torch.Tensor,
        mask: torch.Tensor,
        terminal: torch.Tensor,
        values: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Placements ``[L]`` sampled from pi with the module's generator."""
        log_p = self(features, mask, terminal, values)
        return torch.multinomial(log_p.exp(), 1, generator=self.generator).squeeze(-1)

    @torch.no_grad()
    def record(
        self,
        features: torch.Tensor,
        mask: torch.Tensor,
        terminal: torch.Tensor,
        action: torch.Tensor,
        active: torch.Tensor | None = None,
        values: torch.Tensor | None = None,
    ) -> None:
        """Add the score and the state's Fisher matrix of the placements just taken (under the policy of
        ``values``, as they were sampled) to each active learner's game in progress."""
        allowed = allowed_placements(mask, terminal)
        score, fisher = score_and_fisher(
            features, allowed, action, self.weight, self.temperature, fisher=self.natural, values=values
        )
        live = torch.ones(self.learners, dtype=torch.bool) if active is None else active.to(torch.bool)
        self.game_score += torch.where(live.unsqueeze(-1), score, 0.0)
        if fisher is not None:
            self.game_fisher += torch.where(live.view(-1, 1, 1), fisher, 0.0)

    @torch.no_grad()
    def end_games(self, done: torch.Tensor, returns: torch.Tensor) -> torch.Tensor:
        """Close the games of the learners flagged in ``done`` ``[L]`` with their ``returns`` ``[L]``; the
        learners that reach ``games_per_update`` games take a gradient step. Returns which did ``[L]``."""
        d = done.to(torch.bool)
        advantage = torch.where(d, returns.to(torch.float64) - self.baseline, 0.0)
        self.gradient_sum += advantage.unsqueeze(-1) * self.game_score
        self.fisher_sum += torch.where(d.view(-1, 1, 1), self.game_fisher, 0.0)
        self.games_in_update += d.to(torch.int64)
        decay = torch.where(d, torch.tensor(self.baseline_decay, dtype=torch.float64), 1.0)
        self.baseline_num = decay * self.baseline_num + torch.where(d, returns.to(torch.float64), 0.0)
        self.baseline_den = decay * self.baseline_den + d.to(torch.float64)
        self.game_score = torch.where(d.unsqueeze(-1), 0.0, self.game_score)
        self.game_fisher = torch.where(d.view(-1, 1, 1), 0.0, self.game_fisher)

        step = self.games_in_update >= self.games_per_update
        if bool(step.any()):
            k = self.games_in_update.clamp(min=1).to(torch.float64)
            direction = self.gradient_sum / k.unsqueeze(-1)
            if self.natural:
                direction = natural_direction(direction, self.fisher_sum / k.view(-1, 1, 1), self.damping)
            self.weight += torch.where(step.unsqueeze(-1), self.lr * direction, 0.0)
            self.gradient_sum = torch.where(step.unsqueeze(-1), 0.0, self.gradient_sum)
            self.fisher_sum = torch.where(step.view(-1, 1, 1), 0.0, self.fisher_sum)
            self.games_in_update = torch.where(step, 0, self.games_in_update)
            self.updates += step.to(torch.int64)
        return step

    _STATE = (
        "game_score",
        "game_fisher",
        "gradient_sum",
        "fisher_sum",
        "games_in_update",
        "baseline_num",
        "baseline_den",
        "updates",
    )

    def learner_state(self) -> dict[str, torch.Tensor]:
        """The weights, the games and updates in progress and the sampler: what a resumed run continues."""
        state = {k: getattr(self, k).clone() for k in self._STATE}
        return {"weight": self.weight.detach().clone(), **state, "generator": self.generator.get_state()}

    def load_learner_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore :meth:`learner_state`'s output (same learners and features)."""
        self.weight.copy_(state["weight"])
        for k in self._STATE:
            setattr(self, k, state[k].clone())
        self.generator.set_state(state["generator"])
