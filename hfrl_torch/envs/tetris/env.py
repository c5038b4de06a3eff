"""``TetrisEnv``: a natively batched TorchRL environment over the Tetris engines.

An action is a placement index; the observation holds the features of every
placement's afterstate (so value-based agents score all placements in one
matmul), the action mask, the board and the current piece. Reward = lines
cleared by the placement. Each game's pieces come from its own seed.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from hfrl_torch import keys
from hfrl_torch.envs.tetris.features import feature_id, feature_size
from hfrl_torch.envs.tetris.pieces import placement_table
from hfrl_torch.envs.tetris.rules import TetrisRules

ENGINES = ("auto", "numba", "torch")


def make_engine(rules: TetrisRules, batch: int, features: str, engine: str, device: torch.device):
    """The numba engine on CPU, the torch engine elsewhere (or as asked)."""
    if engine not in ENGINES:
        raise ValueError(f"engine={engine!r} is invalid; allowed: {', '.join(ENGINES)}")
    if engine == "auto":
        engine = "numba" if device.type == "cpu" else "torch"
    if engine == "numba":
        if device.type != "cpu":
            raise ValueError(
                f"engine='numba' runs on the CPU only, not on device={device}; use engine='torch'"
            )
        from hfrl_torch.envs.tetris.engine_numba import NumbaEngine

        return NumbaEngine(rules, batch, feature_id(features))
    from hfrl_torch.envs.tetris.engine_torch import TorchEngine

    return TorchEngine(rules, batch, feature_id(features), device=device)


class TetrisEnv(EnvBase):
    """Batched Tetris under the simplified rules (see ``TetrisRules``).

    :param batch: number of boards B (``batch_size=[B]``).
    :param rules: board size and rule options.
    :param features: afterstate feature set: ``bt``, ``knox``, ``dellacherie`` or ``dt``.
    :param engine: ``auto`` (numba on CPU, torch on GPU), ``numba`` or ``torch``.
    :param max_pieces: truncate a game after this many pieces (0 = never).

    Reset accepts an optional ``reset_game_seed`` [B] entry to play given games (its own key, so
    that the ``game_seed`` observation a partial reset carries along never replays a game);
    otherwise seeds come from the env's generator (see :meth:`set_seed`).

    Masks, TorchRL's way: every observation carries ``action_mask`` [B, A] (the valid placements), and the
    env keeps its own action spec's mask up to date, so the bare env's random actions are valid. A
    ``TransformedEnv`` holds a copy of that spec which the env cannot reach: put TorchRL's ``ActionMask()``
    among its transforms (anywhere in the ``Compose``) so that random actions (``rollout`` without a policy,
    a collector's ``init_random_frames``, ``check_env_specs``) follow the mask. A policy that is handed a spec
    (``RandomPolicy``, ``EGreedyModule``) keeps its own copy: give it ``action_mask_key`` where it takes one.

    Example:
        >>> env = TetrisEnv(batch=4, rules=TetrisRules(10, 10))
        >>> td = env.reset()
        >>> td["afterstate_features"].shape
        torch.Size([4, 34, 21])
        >>> env = TransformedEnv(TetrisEnv(batch=4), Compose(StepCounter(), ActionMask()))
        >>> env.rollout(200, break_when_any_done=False)["step_count"].shape  # random valid placements
        torch.Size([4, 200, 1])
    """

    def __init__(
        self,
        batch: int = 1,
        rules: TetrisRules | None = None,
        features: str = "bt",
        engine: str = "auto",
        max_pieces: int = 0,
        device: str | torch.device = "cpu",
        seed: int | None = None,
    ) -> None:
        device = torch.device(device)
        super().__init__(device=device, batch_size=torch.Size([batch]))
        self.rules = rules if rules is not None else TetrisRules()
        self.features = features
        self.max_pieces = max_pieces
        self.engine = make_engine(self.rules, batch, features, engine, device)
        self.table = placement_table(self.rules.width)
        self.num_actions = self.table.max_actions
        self.num_features = feature_size(feature_id(features), self.rules.width)
        self._lines = torch.zeros(batch, dtype=torch.int64, device=device)
        self._game_seeds = torch.zeros(batch, dtype=torch.int64, device=device)
        self._rng = torch.Generator()
        self._make_specs()
        self.set_seed(0 if seed is None else seed)

    def _make_specs(self) -> None:
        b, a, f = self.batch_size[0], self.num_actions, self.num_features
        h, w = self.rules.height, self.rules.width
        shape = self.batch_size
        obs = {
            keys.AFTERSTATE_FEATURES: Unbounded(shape=(b, a, f), dtype=torch.float32, device=self.device),
            keys.AFTERSTATE_TERMINAL: Binary(n=a, shape=(b, a), dtype=torch.bool, device=self.device),
            keys.STATE_FEATURES: Unbounded(shape=(b, f), dtype=torch.float32, device=self.device),
            keys.ACTION_MASK: Binary(n=a, shape=(b, a), dtype=torch.bool, device=self.device),
            keys.BOARD: Binary(n=w, shape=(b, h, w), dtype=torch.bool, device=self.device),
            keys.PIECE: Categorical(7, shape=shape, device=self.device),
            keys.LINES: Unbounded(shape=(b, 1), dtype=torch.int64, device=self.device),
            keys.PIECES_PLACED: Unbounded(shape=(b, 1), dtype=torch.int64, device=self.device),
            keys.GAME_SEED: Bounded(0, 2**62, shape=shape, dtype=torch.int64, device=self.device),
        }
        if self.rules.preview:
            obs[keys.NEXT_PIECE] = Categorical(7, shape=shape, device=self.device)
        self.observation_spec = Composite(obs, shape=shape, device=self.device)
        self.action_spec = Categorical(
            a, shape=shape, device=self.device, mask=torch.ones(b, a, dtype=torch.bool, device=self.device)
        )
        self.reward_spec = Unbounded(shape=(b, 1), dtype=torch.float32, device=self.device)
        flag = Categorical(2, shape=(b, 1), dtype=torch.bool, device=self.device)
        self.full_done_spec = Composite(
            {keys.DONE: flag.clone(), keys.TERMINATED: flag.clone(), keys.TRUNCATED: flag.clone()},
            shape=shape,
            device=self.device,
        )

    def _observation(self) -> TensorDict:
        feats, mask, terminal, _ = self.engine.afterstates()
        dev = self.device
        mask = mask.to(dev, copy=True)  # the engine reuses its buffers: every observation owns its mask
        # a finished board keeps one valid action so that masked sampling stays defined
        mask[:, 0] |= ~mask.any(-1)
        self.action_spec.update_mask(mask.clone())
        out = {
            keys.AFTERSTATE_FEATURES: feats.to(dev, copy=True),
            keys.AFTERSTATE_TERMINAL: terminal.to(dev, copy=True),
            keys.STATE_FEATURES: self.engine.board_features().to(dev),
            keys.ACTION_MASK: mask,
            keys.BOARD: self.engine.boards().to(dev),
            keys.PIECE: torch.as_tensor(self.engine.pieces, device=dev).clone(),
            keys.LINES: self._lines.unsqueeze(-1).clone(),
            keys.PIECES_PLACED: self._pieces_placed().unsqueeze(-1),
            keys.GAME_SEED: self._game_seeds.clone(),
        }
        if self.rules.preview:
            out[keys.NEXT_PIECE] = self.engine.next_pieces().to(dev)
        return TensorDict(out, batch_size=self.batch_size, device=dev)

    def _pieces_placed(self) -> torch.Tensor:
        """Pieces placed in each board's current game: the engine's index into its piece sequence."""
        return torch.as_tensor(self.engine.index, device=self.device).clone()

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        b = self.batch_size[0]
        if tensordict is not None and keys.RESET in tensordict:
            mask = tensordict.get(keys.RESET).reshape(b).to(torch.bool)
        else:
            mask = torch.ones(b, dtype=torch.bool, device=self.device)
        fresh = torch.randint(0, 2**62, (b,), generator=self._rng, dtype=torch.int64).to(self.device)
        if tensordict is not None and keys.RESET_GAME_SEED in tensordict:
            fresh = tensordict.get(keys.RESET_GAME_SEED).reshape(b).to(torch.int64).to(self.device)
        self._game_seeds = torch.where(mask, fresh, self._game_seeds)
        self._lines = torch.where(mask, 0, self._lines)
        self.engine.reset(mask.to(self.engine.device), self._game_seeds.to(self.engine.device))
        td = self._observation()
        zeros = torch.zeros(b, 1, dtype=torch.bool, device=self.device)
        td.set(keys.DONE, zeros.clone())
        td.set(keys.TERMINATED, zeros.clone())
        td.set(keys.TRUNCATED, zeros.clone())
        return td

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        action = tensordict.get(keys.ACTION).reshape(self.batch_size[0]).to(torch.int64)
        valid = self.action_spec.mask.gather(-1, action.clamp(0, self.num_actions - 1).unsqueeze(-1)).squeeze(
            -1
        )
        live = torch.as_tensor(self.engine.alive, device=self.device)
        bad = live & (~valid | (action < 0) | (action >= self.num_actions))
        if bool(bad.any()):
            i = int(bad.nonzero()[0, 0])
            raise ValueError(
                f"action={int(action[i])} on board {i} is not a valid placement for piece "
                f"{int(self.engine.pieces[i])}; allowed: the indices where action_mask is True (random "
                "actions through a TransformedEnv need torchrl's ActionMask() among its transforms)"
            )
        lines = self.engine.step(action.to(self.engine.device)).to(self.device)
        self._lines += lines
        alive = torch.as_tensor(self.engine.alive, device=self.device)
        terminated = ~alive
        truncated = alive & (self.max_pieces > 0) & (self._pieces_placed() >= self.max_pieces)
        td = self._observation()
        td.set(keys.REWARD, lines.to(torch.float32).unsqueeze(-1))
        td.set(keys.TERMINATED, terminated.unsqueeze(-1))
        td.set(keys.TRUNCATED, truncated.unsqueeze(-1))
        td.set(keys.DONE, (terminated | truncated).unsqueeze(-1))
        return td

    def _set_seed(self, seed: int | None) -> None:
        self._rng.manual_seed(0 if seed is None else int(seed))

    _ENGINE_STATE = ("rows", "heights", "pieces", "keys", "index", "alive")

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Every board's game in progress and the seed generator: what :meth:`load_state_dict` continues."""
        state = {k: torch.as_tensor(getattr(self.engine, k)).clone().cpu() for k in self._ENGINE_STATE}
        return {
            **state,
            "lines": self._lines.cpu(),
            "game_seeds": self._game_seeds.cpu(),
            "rng": self._rng.get_state(),
        }

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> TensorDictBase:
        """Continue the games of :meth:`state_dict`; returns the observation of the boards as they are."""
        for k in self._ENGINE_STATE:
            current = getattr(self.engine, k)
            saved = state[k]
            if tuple(saved.shape) != tuple(current.shape):
                raise ValueError(
                    f"Tetris state {k!r} of shape {tuple(saved.shape)}; this env holds {tuple(current.shape)}"
                )
            if isinstance(current, torch.Tensor):
                current.copy_(saved.to(current.device))
            else:
                current[...] = saved.numpy()
        self._lines = state["lines"].to(self.device).clone()
        self._game_seeds = state["game_seeds"].to(self.device).clone()
        self._rng.set_state(state["rng"])
        td = self._observation()
        alive = torch.as_tensor(self.engine.alive, device=self.device).unsqueeze(-1)
        td.set(keys.DONE, ~alive)
        td.set(keys.TERMINATED, ~alive)
        td.set(keys.TRUNCATED, torch.zeros_like(alive))
        return td
