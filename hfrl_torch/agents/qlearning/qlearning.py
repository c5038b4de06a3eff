"""Q-learning for Tetris placements with a linear Q over afterstate features, many learners at once.

Watkins (1989), "Learning from Delayed Rewards"; the thesis's Algorithm 4 (section 3.3), with the table
replaced by a linear function of the features of the board a placement leaves, as in the thesis's
experiments (Figure 3.4: about 38 lines per game after about 200 games on 10 x 20).
"""

from __future__ import annotations

import torch
from torch import nn


def allowed_placements(mask: torch.Tensor, terminal: torch.Tensor) -> torch.Tensor:
    """The placements a player considers ``[B, A]``: the valid ones that do not end the game, or every
    valid one when all of them end it (as :func:`hfrl_torch.models.linear.greedy_placement` chooses)."""
    safe = mask & ~terminal
    return torch.where(safe.any(-1, keepdim=True), safe, mask)


class LinearQLearning(nn.Module):
    """Q-learning with Q(s, a) = w . f(s'_a) + b, one independent learner per board (Algorithm 4).

    f(s'_a) is the feature vector of the afterstate of placement a (BT 21 by default), so the linear Q
    scores every placement of a board in one product. Actions are epsilon-greedy over the allowed
    placements (:func:`allowed_placements`): with probability epsilon a uniformly random one, else the
    greedy one, the first on ties. After each placement every active learner makes the one-step TD update

        delta = r + gamma * max_a' Q(s', a') - Q(s, a)      (max over the allowed a'; 0 at game end)
        w <- w + alpha * delta * f(s'_a),   b <- b + alpha * delta

    with r the lines the placement cleared. The bias b (the thesis's constant feature) shifts every
    placement's value alike, so the greedy policy is the linear afterstate policy w, which is what a
    checkpoint stores. Weights are float64 and start at 0.

    :param num_features: F, the size of the env's feature set.
    :param learners: L, independent learners (weights ``[L, F]``, one row per board).
    :param alpha: the step size.
    :param gamma: the discount factor.
    :param seed: seeds the generator of the epsilon-greedy draws, so a run is a function of its seeds.

    Example:
        >>> q = LinearQLearning(2, learners=1, alpha=0.5, gamma=0.9)
        >>> f = torch.tensor([[1.0, 2.0]], dtype=torch.float64)
        >>> _ = q.td_update(f, torch.tensor([1.0]), None, None, None, torch.tensor([True]))
        >>> q.weight.tolist(), q.bias.tolist()
        ([[0.5, 1.0]], [0.5])
    """

    def __init__(self, num_features: int, learners: int, alpha: float, gamma: float, seed: int = 0) -> None:
        super().__init__()
        if num_features < 1 or learners < 1:
            raise ValueError(f"need num_features >= 1 and learners >= 1, got {num_features} and {learners}")
        if not alpha > 0 or not 0 <= gamma <= 1:
            raise ValueError(f"need alpha > 0 and gamma in 0..1, got {alpha!r} and {gamma!r}")
        self.weight = nn.Parameter(
            torch.zeros(learners, num_features, dtype=torch.float64), requires_grad=False
        )
        self.bias = nn.Parameter(torch.zeros(learners, dtype=torch.float64), requires_grad=False)
        self.alpha = float(alpha)
        self.gamma = float(gamma)
        self.generator = torch.Generator().manual_seed(int(seed))

    @property
    def learners(self) -> int:
        return self.weight.shape[0]

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Q ``[L, A]`` of every placement from its afterstate features ``[L, A, F]``."""
        return torch.einsum("laf,lf->la", features.to(torch.float64), self.weight) + self.bias.unsqueeze(-1)

    @torch.no_grad()
    def act(
        self,
        features: torch.Tensor,
        mask: torch.Tensor,
        terminal: torch.Tensor,
        epsilon: torch.Tensor | float,
    ) -> torch.Tensor:
        """Epsilon-greedy placements ``[L]`` over the allowed placements (epsilon per learner or one)."""
        allowed = allowed_placements(mask, terminal)
        greedy = self(features).masked_fill(~allowed, -torch.inf).argmax(-1)
        uniform = torch.rand(allowed.shape, generator=self.generator, dtype=torch.float64)
        random = uniform.masked_fill(~allowed, -1.0).argmax(-1)  # a uniform draw among the allowed
        explore = torch.rand(self.learners, generator=self.generator, dtype=torch.float64) < torch.as_tensor(
            epsilon, dtype=torch.float64
        )
        return torch.where(explore, random, greedy)

    @torch.no_grad()
    def td_update(
        self,
        chosen: torch.Tensor,
        reward: torch.Tensor,
        next_features: torch.Tensor | None,
        next_mask: torch.Tensor | None,
        next_terminal: torch.Tensor | None,
        terminated: torch.Tensor,
        active: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """One Q-learning step per active learner; returns the TD errors ``[L]`` (0 for inactive ones).

        :param chosen: ``[L, F]`` afterstate features of the placement taken.
        :param reward: ``[L]`` lines it cleared.
        :param next_features: ``[L, A, F]`` afterstate features of every placement in s' (may be None
            when every learner's game ended).
        :param next_mask: ``[L, A]`` valid placements in s'.
        :param next_terminal: ``[L, A]`` placements in s' that end the game.
        :param terminated: ``[L]`` the game ended with this placement: no bootstrap.
        :param active: ``[L]`` learners that learn from this step (default all).
        """
        chosen = chosen.to(torch.float64)
        q = (chosen * self.weight).sum(-1) + self.bias
        future = torch.zeros_like(q)
        if next_features is not None:
            allowed = allowed_placements(next_mask, next_terminal)
            future = self(next_features).masked_fill(~allowed, -torch.inf).amax(-1)
            future = torch.where(terminated | ~allowed.any(-1), 0.0, future)
        delta = reward.to(torch.float64) + self.gamma * future - q
        if active is not None:
            delta = torch.where(active, delta, 0.0)
        self.weight += self.alpha * delta.unsqueeze(-1) * chosen
        self.bias += self.alpha * delta
        return delta

    def learner_state(self) -> dict[str, torch.Tensor]:
        """The weights and the exploration generator: what a resumed run continues."""
        return {
            "weight": self.weight.detach().clone(),
            "bias": self.bias.detach().clone(),
            "generator": self.generator.get_state(),
        }

    def load_learner_state(self, state: dict[str, torch.Tensor]) -> None:
        """Restore :meth:`learner_state`'s output (same learners and features)."""
        self.weight.copy_(state["weight"])
        self.bias.copy_(state["bias"])
        self.generator.set_state(state["generator"])
