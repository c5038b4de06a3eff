"""Keepaway as a batched TorchRL environment with SMDP steps.

``sync="all"`` (default): one ``step`` hands the chosen macro-actions to the fields' keepers with
the ball and then simulates 100 ms cycles (all fields in lock-step; a field that reaches its next
decision or the end of its episode waits for the others) until every field's keeper with the ball
must decide again. ``sync="any"``: one ``step`` applies the actions of the *deciding* fields and
simulates every alive field until at least one must decide or ends (usually one cycle), so no field
idles; ``"deciding"`` [B] says which fields' observation is a real decision.

The reward of a step is, on deciding fields, the number of cycles since the deciding keeper's
previous decision (0 at its first decision), so each keeper's rewards add up to the time the ball
stayed in play after its first decision; 0 on fields that neither decide nor end.

At the end of an episode, ``episode_end_rewards`` [B, n] gives every keeper's cycles since its
own last decision (0 for keepers that never decided): what RLendEpisode needs for each keeper.
The terminal ``reward`` is the entry of the keeper that decided last.
"""

from __future__ import annotations

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import expand_as_right
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from hfrl_torch import keys
from hfrl_torch.envs.keepaway.params import KeepawayConfig
from hfrl_torch.envs.keepaway.simulator import Decision, KeepawaySimulator

EPISODE_END_REWARDS = keys.EPISODE_END_REWARDS
STEP_CYCLES = keys.STEP_CYCLES
SYNC_MODES = ("all", "any")

_OUTPUT_KEYS = (
    keys.OBSERVATION,
    keys.KEEPER,
    keys.ACTION_MASK,
    keys.EPISODE_CYCLES,
    keys.END_CAUSE,
    EPISODE_END_REWARDS,
    STEP_CYCLES,
    keys.DECIDING,
)


class KeepawayEnv(EnvBase):
    """B keepaway fields as one TorchRL environment (Stone, Sutton & Kuhlmann 2005).

    Observation ``"observation"`` [B, 4n + 2m - 3]: the deciding keeper's state variables;
    ``"keeper"`` [B]: which keeper decides; ``"action_mask"`` [B, n] over {Hold, Pass to teammate
    1..n-1} (teammates numbered by distance); action [B] in 0..n-1.

    :param batch_size: number of fields B.
    :param config: the task; keyword arguments override its fields (``preset``, ``keepers``,
        ``takers``, ``length``, ``width``, ``turnover_cycles``, ``movement_noise``,
        ``noisy_observations``, ``decision_period_cycles``, ...).
    :param device: torch device of the simulator and the tensordicts.
    :param seed: seed of the simulator's generator.
    :param max_cycles_per_step: safety bound on the cycles simulated in one step.
    :param sync: ``"all"``: a step runs until every alive field must decide (reset runs a restarted
        field to its first decision); ``"any"``: a step runs until at least one alive field must
        decide or ends, and a restarted field is "not deciding" until its keeper first must decide.
        ``"deciding"`` [B] marks the fields whose observation, keeper and action mask are a decision
        now (every alive field in ``"all"`` mode); actions of the other fields are ignored.
    :param cycle_by_cycle: on the whole-cycle kernels (``kernels="cycle"``), step through the
        simulator's ``step``, one compiled cycle per call, instead of running a step's cycles in one
        compiled call: a hook on ``sim.step`` then sees every cycle (the browser trainer's view). The
        other kernels always do.
    """

    batch_locked = True

    def __init__(
        self,
        batch_size: int = 1,
        config: KeepawayConfig | None = None,
        *,
        device: str | torch.device = "cpu",
        seed: int = 0,
        max_cycles_per_step: int = 100_000,
        sync: str = "all",
        cycle_by_cycle: bool = False,
        **config_overrides: object,
    ) -> None:
        if sync not in SYNC_MODES:
            raise ValueError(f"sync must be one of {SYNC_MODES}, got {sync!r}")
        config = config if config is not None else KeepawayConfig()
        if config_overrides:
            config = config.replace(**config_overrides)
        super().__init__(device=device, batch_size=torch.Size([batch_size]))
        self.config = config
        self.max_cycles_per_step = max_cycles_per_step
        self.sync = sync
        self.sim = KeepawaySimulator(batch_size, config, device=self.device, seed=seed)
        self.whole_steps = self.sim.compiled is not None and not cycle_by_cycle  # a step in one call
        self._make_specs()
        self._outputs = self._blank_outputs()
        self._done = torch.ones(batch_size, dtype=torch.bool, device=self.device)
        # kernels="cycle": the outputs and done flags as numpy views the compiled step writes in place
        # (the tensors are only ever updated in place on that path, so the views stay valid)
        self._arrays = (
            (tuple(self._outputs[k].numpy() for k in _OUTPUT_KEYS), self._done.numpy())
            if self.whole_steps
            else None
        )

    # ------------------------------------------------------------------------- specs

    def _make_specs(self) -> None:
        b, n, a = self.batch_size[0], self.config.keepers, self.config.num_actions
        f = self.config.num_state_vars
        self.observation_spec = Composite(
            {
                keys.OBSERVATION: Unbounded(shape=(b, f), dtype=torch.float32, device=self.device),
                keys.KEEPER: Categorical(n, shape=(b,), dtype=torch.int64, device=self.device),
                keys.ACTION_MASK: Binary(n=a, shape=(b, a), dtype=torch.bool, device=self.device),
                keys.EPISODE_CYCLES: Unbounded(shape=(b,), dtype=torch.int64, device=self.device),
                keys.END_CAUSE: Categorical(3, shape=(b,), dtype=torch.int64, device=self.device),
                EPISODE_END_REWARDS: Unbounded(shape=(b, n), dtype=torch.float32, device=self.device),
                STEP_CYCLES: Unbounded(shape=(b,), dtype=torch.int64, device=self.device),
                keys.DECIDING: Categorical(2, shape=(b,), dtype=torch.bool, device=self.device),
            },
            shape=(b,),
            device=self.device,
        )
        self.action_spec = Categorical(a, shape=(b,), dtype=torch.int64, device=self.device)
        self.reward_spec = Unbounded(shape=(b, 1), dtype=torch.float32, device=self.device)
        self.done_spec = Composite(
            {
                k: Categorical(2, shape=(b, 1), dtype=torch.bool, device=self.device)
                for k in (keys.DONE, keys.TERMINATED, keys.TRUNCATED)
            },
            shape=(b,),
            device=self.device,
        )

    def _blank_outputs(self) -> dict[str, torch.Tensor]:
        return {k: spec.zero() for k, spec in self.observation_spec.items()}

    # ----------------------------------------------------------------------- helpers

    def _run_until_decision(
        self, running: torch.Tensor, restart_ended: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Simulate the ``running`` fields until their keeper with the ball must decide or
        their episode ends. With ``restart_ended`` an episode that ends first is restarted.

        :returns: which fields ended (never with ``restart_ended``), why, and the cycles
            simulated [B].
        """
        sim = self.sim
        running = running.clone()
        ended = torch.zeros_like(running)
        cause = torch.zeros(running.shape, dtype=torch.int64, device=self.device)
        cycles = torch.zeros(running.shape, dtype=torch.int64, device=self.device)
        for _ in range(self.max_cycles_per_step):
            waiting = running & ~sim.decision().must_decide
            if not bool(waiting.any()):
                break
            out = sim.step(None, active=waiting)
            cycles += waiting
            if restart_ended:
                if bool(out.ended.any()):
                    sim.reset(out.ended)
            else:
                ended |= out.ended
                cause = torch.where(out.ended, out.end_cause, cause)
                running &= ~out.ended
        else:
            raise RuntimeError("keepaway: no decision within max_cycles_per_step cycles")
        return ended, cause, cycles

    def _decisions(self) -> tuple[Decision, torch.Tensor]:
        """The simulator's decision and the holder's state variables (the torch path's; the
        whole-cycle path writes them in ``compiled.kernels.env_outputs``)."""
        dec = self.sim.decision()
        return dec, self.sim.observe(dec.holder)[0]

    def _write_decisions(
        self, fields: torch.Tensor, decided: tuple[Decision, torch.Tensor] | None = None
    ) -> None:
        """Store the observation of the keeper with the ball on ``fields`` [B], and which fields
        (alive, keeper with the ball free to choose) decide now."""
        dec, obs = self._decisions() if decided is None else decided
        out = self._outputs
        f = fields
        out[keys.OBSERVATION] = torch.where(f[:, None], obs.to(torch.float32), out[keys.OBSERVATION])
        out[keys.KEEPER] = torch.where(f, dec.holder, out[keys.KEEPER])
        out[keys.ACTION_MASK] = torch.where(f[:, None], True, out[keys.ACTION_MASK])
        out[keys.EPISODE_CYCLES] = torch.where(f, self.sim.state.episode_cycles, out[keys.EPISODE_CYCLES])
        out[keys.DECIDING] = ~self._done & dec.must_decide

    def _result(self, reward: torch.Tensor | None) -> TensorDict:
        done = self._done.unsqueeze(-1)
        td = TensorDict(
            {k: v.clone() for k, v in self._outputs.items()},
            batch_size=self.batch_size,
            device=self.device,
        )
        td.set(keys.DONE, done.clone())
        td.set(keys.TERMINATED, done.clone())
        td.set(keys.TRUNCATED, torch.zeros_like(done))
        if reward is not None:
            td.set(keys.REWARD, reward.to(torch.float32).unsqueeze(-1))
        return td

    # ------------------------------------------------------------------ EnvBase API

    def _compiled_result(self, reward: torch.Tensor | None) -> TensorDict:
        """:meth:`_result` without TensorDict's per-entry checks: every tensor here is a fresh CPU
        tensor of this env's batch size (``kernels="cycle"``)."""
        done = self._done.unsqueeze(-1)
        source = {k: v.clone() for k, v in self._outputs.items()}
        source[keys.DONE] = done.clone()
        source[keys.TERMINATED] = done.clone()
        source[keys.TRUNCATED] = torch.zeros_like(done)
        if reward is not None:
            source[keys.REWARD] = reward.unsqueeze(-1)
        # private: the public constructor's per-entry checks cost ~33 us a call (~5 % of a B = 1 step)
        return TensorDict._new_unsafe(source, batch_size=self.batch_size, device=self.device)

    def _compiled_reset(self, mask: torch.Tensor) -> TensorDict:
        """:meth:`_reset` on the whole-cycle path: restart, (``"all"``) run to the first decisions and
        write the outputs in compiled calls, with no torch work per field."""
        outputs, done = self._arrays
        mask = mask.to(torch.bool).contiguous().numpy()
        sim = self.sim
        sim.compiled.env_reset(sim.state, mask, self.sync == "all", self.max_cycles_per_step, outputs, done)
        return self._compiled_result(None)

    def _compiled_step(self, actions: torch.Tensor) -> TensorDict:
        """:meth:`_step` on the whole-cycle path: every alive field advanced, then its outputs, reward
        and done flag written, in two compiled calls."""
        outputs, done = self._arrays
        reward = torch.empty(self.batch_size[0], dtype=torch.float32)
        sim = self.sim
        sim.compiled.env_step(
            sim.state,
            actions.contiguous().numpy(),
            ~done,
            self.sync,
            self.max_cycles_per_step,
            outputs,
            done,
            reward.numpy(),
        )
        return self._compiled_result(reward)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: object) -> TensorDictBase:
        if tensordict is not None and keys.RESET in tensordict:
            mask = tensordict.get(keys.RESET).reshape(-1).to(self.device)
        else:
            mask = torch.ones(self.batch_size, dtype=torch.bool, device=self.device)
        if self.whole_steps:
            return self._compiled_reset(mask)
        self.sim.reset(mask)
        if self.sync == "all":  # "any": the restarted fields reach their first decision in later steps
            self._run_until_decision(mask, restart_ended=True)
        out = self._outputs
        out[keys.END_CAUSE] = torch.where(mask, 0, out[keys.END_CAUSE])
        out[EPISODE_END_REWARDS] = torch.where(mask[:, None], 0.0, out[EPISODE_END_REWARDS])
        out[STEP_CYCLES] = torch.where(mask, 0, out[STEP_CYCLES])
        self._done = self._done & ~mask
        self._write_decisions(mask)
        return self._result(None)

    def maybe_reset(self, tensordict: TensorDictBase) -> TensorDictBase:
        """:meth:`EnvBase.maybe_reset`, with the reset's entries put in place of the root's instead of blended
        with ``TensorDict.where``: ``_reset`` returns every field's current outputs, not only the restarted
        fields', so only the root's other entries (the action) need TorchRL's zeros on the restarted fields.
        The same tensordicts (``tests/envs/keepaway/test_keepaway_env.py``); the blend of a dozen keys was a
        fifth of a step at one field per learner. A ``TransformedEnv`` around this env keeps TorchRL's blend:
        its transforms' reset entries need not cover every field."""
        if not self.any_done(tensordict):  # (writes "_reset" where it is True)
            return tensordict
        fresh = self._reset(tensordict.select(keys.RESET))  # done, terminated and truncated complete
        keep = ~tensordict.pop(keys.RESET).view(-1)
        if bool(keep.any()):  # (every field restarted: TorchRL updates, keeping the other entries whole)
            for key, value in tensordict.items():
                if key not in fresh:
                    kept = expand_as_right(keep, value) if isinstance(value, torch.Tensor) else keep
                    tensordict.set(key, value.where(kept, torch.zeros_like(value)))
        return tensordict.update(fresh)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        sim = self.sim
        actions = tensordict.get(keys.ACTION).reshape(-1).to(self.device).long()
        # the simulator reads an action only where the keeper must decide: in both modes exactly the
        # fields flagged "deciding" by the previous step or reset, so other fields' actions are ignored
        if self.whole_steps:
            return self._compiled_step(actions)
        alive = ~self._done
        first = sim.step(actions, active=alive)
        ended, cause = first.ended.clone(), first.end_cause.clone()
        if self.sync == "all":
            later_ended, later_cause, cycles = self._run_until_decision(alive & ~ended, restart_ended=False)
        else:
            later_ended, later_cause, cycles = self._run_until_any_decision(alive & ~ended, bool(ended.any()))
        ended |= later_ended
        cause = torch.where(later_ended, later_cause, cause)
        cycles = cycles + alive.long()

        state = sim.state
        decided = self._decisions()
        dec = decided[0]
        deciding = alive & ~ended & dec.must_decide
        last = state.last_decision.gather(1, dec.holder.unsqueeze(-1)).squeeze(-1)
        decision_reward = torch.where(last >= 0, state.episode_cycles - last, torch.zeros_like(last))
        latest = state.last_decision.max(-1).values
        end_reward = torch.where(latest >= 0, state.episode_cycles - latest, state.episode_cycles)
        reward = torch.where(
            ended, end_reward, torch.where(deciding, decision_reward, torch.zeros_like(last))
        )

        self._done = self._done | ended
        self._write_decisions(alive, decided)
        out = self._outputs
        out[keys.END_CAUSE] = torch.where(ended, cause, torch.where(alive, 0, out[keys.END_CAUSE]))
        end_rewards = sim.episode_end_rewards().to(torch.float32)
        out[EPISODE_END_REWARDS] = torch.where(
            ended[:, None], end_rewards, torch.where(alive[:, None], 0.0, out[EPISODE_END_REWARDS])
        )
        out[STEP_CYCLES] = torch.where(alive, cycles, 0)
        return self._result(reward)

    def _run_until_any_decision(
        self, running: torch.Tensor, stop: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``sync="any"``: simulate the ``running`` fields until one of them must decide or ends
        (nothing if ``stop``, i.e. a field already ended this step).

        :returns: which fields ended, why, and the cycles simulated [B].
        """
        sim = self.sim
        running = running.clone()
        ended = torch.zeros_like(running)
        cause = torch.zeros(running.shape, dtype=torch.int64, device=self.device)
        cycles = torch.zeros(running.shape, dtype=torch.int64, device=self.device)
        if stop:
            return ended, cause, cycles
        for _ in range(self.max_cycles_per_step):
            if bool((running & sim.decision().must_decide).any() | ~running.any()):
                return ended, cause, cycles
            out = sim.step(None, active=running)  # no running field must decide: no action is read
            cycles += running
            ended |= out.ended
            cause = torch.where(out.ended, out.end_cause, cause)
            running &= ~out.ended
            if bool(out.ended.any()):
                return ended, cause, cycles
        raise RuntimeError("keepaway: no decision within max_cycles_per_step cycles")

    # ------------------------------------------------------------------ checkpoints

    def state_dict(self) -> dict[str, object]:
        """The simulator's play in progress and this env's own bookkeeping (the outputs of the last step,
        which fields' episodes are over): what :meth:`load_state_dict` continues exactly."""
        return {
            "sim": self.sim.state_dict(),
            "outputs": {k: v.clone().cpu() for k, v in self._outputs.items()},
            "done": self._done.clone().cpu(),
        }

    def load_state_dict(self, state: dict[str, object]) -> None:
        """Continue the fields of :meth:`state_dict` (same number of fields and task)."""
        outputs, done = state["outputs"], state["done"]
        if not isinstance(outputs, dict) or set(outputs) != set(self._outputs):
            held = sorted(outputs) if isinstance(outputs, dict) else type(outputs).__name__
            raise ValueError(f"keepaway env outputs hold {held}; expected {sorted(self._outputs)}")
        for k, now in self._outputs.items():
            v = outputs[k]
            if not isinstance(v, torch.Tensor) or v.shape != now.shape or v.dtype != now.dtype:
                raise ValueError(f"keepaway env output {k!r} does not fit this env's {now.dtype} {now.shape}")
        if not isinstance(done, torch.Tensor) or done.shape != self._done.shape:
            raise ValueError(f"keepaway env 'done' does not fit this env's {tuple(self._done.shape)} fields")
        self.sim.load_state_dict(state["sim"])
        for k, v in outputs.items():  # in place: the compiled path's views of them stay valid
            self._outputs[k].copy_(v)
        self._done.copy_(done)

    def _set_seed(self, seed: int | None) -> None:
        if seed is not None:
            self.sim.seed(seed)
