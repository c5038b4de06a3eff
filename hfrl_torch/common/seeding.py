"""Every random stream of a run, from its one root seed (``cfg.seed``).

Each component of a run that draws (the games, the agent, the simulated trainer, the fusion...) seeds its own
generator with ``component_seed(root, component)``, and :data:`STREAMS` names every component, so that no two
components of a run share a stream: ``tests/common/test_seeding.py`` checks that every component's seed
differs from every other's for the roots 0 to 10,000.

Two kinds of stream:

- :class:`Linear`: ``scale * root + offset``, the seeds the components had before this table (kept so
  that the documented results stand). Linear streams of one root never meet: the one of scale 1 has offset
  0, those of scale 2 positive offsets.
- :class:`Hashed`: 62 bits drawn from a generator seeded with ``root * 1_000_003 + iteration * 7919 +
  number``: the CE method's per-iteration streams (stateless, so a resumed run draws what an uninterrupted
  one does), and the streams that collided under the old offsets (``trainer``, ``eval_games``,
  ``reference``), which no small linear seed can meet.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

RESEED_STEP = 1_000_003  # a linear stream's n-th reseeding (a resumed keepaway run): n steps of this further


@dataclass(frozen=True)
class Linear:
    """``scale * root + offset`` (plus ``RESEED_STEP`` per reseeding)."""

    scale: int
    offset: int

    def seed(self, root: int, reseeds: int = 0) -> int:
        return self.scale * root + self.offset + RESEED_STEP * reseeds


@dataclass(frozen=True)
class Hashed:
    """62 bits drawn from a generator seeded with the root, ``iteration`` and the stream's ``number``."""

    number: int

    def seed(self, root: int, iteration: int = 0) -> int:
        g = torch.Generator().manual_seed((root * 1_000_003 + iteration * 7919 + self.number) % (2**63 - 1))
        return int(torch.randint(0, 2**62, (1,), generator=g, dtype=torch.int64))


STREAMS: dict[str, Linear | Hashed] = {
    # the training games (Tetris) or fields (keepaway); a resumed keepaway run reseeds it (extra: resumes)
    "env": Linear(1, 0),
    # the agent's own draws: PG's and Q-learning's sampling, the Sarsa keepers' exploration and ties,
    # DQN's network initialisation and TorchRL's exploration (the global torch seed)
    "agent": Linear(2, 1),
    "timing": Linear(2, 2),  # the simulated trainer's human-like timing (delays, fatigue, absence)
    "fusion": Linear(2, 5),  # the fusion rule's draws (e.g. control sharing's)
    "bandit": Linear(2, 7),  # the bandit weight's draws (fusion.weight=bandit or adaptive)
    "replay": Linear(2, 11),  # DQN's replay sampling; PPO's minibatches (a run has one or the other)
    "human_model": Linear(2, 13),  # Deep TAMER's replay sampling
    # the CE method, per iteration (extra: the iteration)
    "cem_candidates": Hashed(0),
    "cem_games": Hashed(1),
    "cem_eval": Hashed(2),
    "watched_game": Hashed(3),  # the game the trainer watches (CE + a trainer)
    "cem_fusion": Hashed(4),  # the fusion's draws in that game
    # moved off colliding linear seeds: trainer was 2 * root + 1, the agent's; eval_games was root + 10_007,
    # bandit's at root 10_000, replay's at 9_996 and human_model's at 9_994; reference was root + 7
    "trainer": Hashed(5),  # the simulated trainer (Tetris or keepaway oracle): which events it gives
    "eval_games": Hashed(6),  # the greedy evaluation's games, which training does not play
    "reference": Hashed(7),  # the keepaway oracle's reference keepers (a checkpoint's ties)
}


def component_seed(root: int, component: str, *extra: int) -> int:
    """The seed of ``component``'s generator in the run of root seed ``root`` (``extra``: see
    :data:`STREAMS`)."""
    return STREAMS[component].seed(int(root), *extra)


def component_generator(root: int, component: str, *extra: int) -> torch.Generator:
    """A CPU generator seeded with :func:`component_seed`."""
    return torch.Generator().manual_seed(component_seed(root, component, *extra))
