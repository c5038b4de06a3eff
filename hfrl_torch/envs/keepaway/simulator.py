"""The batched keepaway simulator: B independent fields advanced in lock-step, one 100 ms
cycle per call, with the keepers' and takers' skills built in. Only the choice of the keeper
with the ball (HoldBall or PassBall(k)) comes from outside.

Layer: engine. No TorchRL here; env.py wraps this in an EnvBase.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.compiled import Advance, CompiledCycle
from hfrl_torch.envs.keepaway.keepers import fastest_keeper, keeper_commands
from hfrl_torch.envs.keepaway.params import KeepawayConfig, resolve_kernels
from hfrl_torch.envs.keepaway.perception import (
    after_collision,
    extrapolate,
    observe,
    own_truth,
    see_phases,
    sees_now,
)
from hfrl_torch.envs.keepaway.physics import (
    DASH_KIND,
    KICK_KIND,
    TURN_KIND,
    dash_acceleration,
    kick_acceleration,
    move,
    norm,
    resolve_collisions,
    turn_body,
)
from hfrl_torch.envs.keepaway.referee import (
    END_RUNNING,
    ball_in_region,
    end_cause,
    reset_positions,
    update_turnover_counter,
)
from hfrl_torch.envs.keepaway.skills import (
    ball_rest_point,
    get_open_grid,
    intercept_estimate,
    predict_ball,
)
from hfrl_torch.envs.keepaway.state_vars import (
    gather_points,
    keeper_state_variables,
    quantised_view,
    teammate_order,
)
from hfrl_torch.envs.keepaway.takers import taker_commands

HOLD = 0


@dataclass
class KeepawayState:
    """Everything that changes during play, for B fields.

    Objects are stored together: index 0 is the ball, 1..n the keepers, n+1..n+m the takers.
    """

    pos: Tensor  # [B, 1 + n + m, 2]
    vel: Tensor  # [B, 1 + n + m, 2]
    body: Tensor  # [B, 1 + n + m] body angles (the ball's entry is unused)
    counter: Tensor  # [B] cycles of taker possession
    episode_cycles: Tensor  # [B] cycles since the episode started
    last_decision: Tensor  # [B, n] cycle of each keeper's last decision, -1 before its first
    prev_holder: Tensor  # [B] keeper that executed its macro-action last cycle, -1 if none
    pass_target: Tensor  # [B] that keeper's pass target, -1 for HoldBall
    action_start: Tensor  # [B] cycle of that macro-action's decision
    clock: Tensor  # [B] cycles since the simulator started, across episodes (the server's clock)
    see_phase: Tensor  # [B, P] each player's see timing (P = 0 columns without timed sees)
    seen_pos: Tensor  # [B, P, 1 + n + m, 2] each player's belief (P = 0 under exact perception)
    seen_vel: Tensor  # [B, P, 1 + n + m, 2]
    seen_body: Tensor  # [B, P, 1 + n + m]
    keepers: int
    takers: int

    @property
    def ball_pos(self) -> Tensor:
        """Ball position [B, 2]."""
        return self.pos[:, 0]

    @property
    def ball_vel(self) -> Tensor:
        """Ball velocity [B, 2]."""
        return self.vel[:, 0]

    @property
    def keeper_pos(self) -> Tensor:
        """Keeper positions [B, n, 2]."""
        return self.pos[:, 1 : 1 + self.keepers]

    @property
    def taker_pos(self) -> Tensor:
        """Taker positions [B, m, 2]."""
        return self.pos[:, 1 + self.keepers :]

    @property
    def batch_size(self) -> int:
        """Number of fields B."""
        return self.pos.shape[0]

    def tensors(self) -> dict[str, Tensor]:
        """The state's tensors by field name."""
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.type == "Tensor"}

    def where(self, mask: Tensor, other: KeepawayState) -> KeepawayState:
        """This state on fields where ``mask`` [B] is true, ``other`` elsewhere."""
        picked = {}
        for name, value in self.tensors().items():
            m = mask.reshape(-1, *([1] * (value.dim() - 1)))
            picked[name] = torch.where(m, value, getattr(other, name))
        return dataclasses.replace(self, **picked)

    def clone(self) -> KeepawayState:
        """A deep copy."""
        return dataclasses.replace(
            self, **{k: v.clone(memory_format=torch.contiguous_format) for k, v in self.tensors().items()}
        )

    def field(self, index: int) -> KeepawayState:
        """The state of one field as a batch of one."""
        return dataclasses.replace(self, **{k: v[index : index + 1] for k, v in self.tensors().items()})


@dataclass
class Decision:
    """Who has the ball at the current state of every field."""

    holder: Tensor  # [B] keeper closest to the ball
    kickable: Tensor  # [B] whether it can kick the ball
    must_decide: Tensor  # [B] it has the ball and no macro-action is running


@dataclass
class CycleOutcome:
    """What one cycle did to every field."""

    ended: Tensor  # [B] the episode ended this cycle
    end_cause: Tensor  # [B] 0 running, 1 out, 2 taken
    episode_cycles: Tensor  # [B] episode length so far (the duration where ended)
    episode_end_rewards: Tensor  # [B, n] cycles since each keeper's last decision (0 if none)


class KeepawaySimulator:
    """B keepaway fields on one device, deterministic for a seed.

    :param batch_size: number of fields B.
    :param config: the task (preset, numbers of players, region, noise, decision period).
    :param device: torch device; all state lives there.
    :param seed: seed of the simulator's own ``torch.Generator``.
    """

    def __init__(
        self,
        batch_size: int,
        config: KeepawayConfig | None = None,
        *,
        device: str | torch.device = "cpu",
        seed: int = 0,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.config = config if config is not None else KeepawayConfig()
        self.physics = self.config.physics
        self.batch_size = batch_size
        self.device = torch.device(device)
        self.dtype = dtype
        self.kernels = resolve_kernels(self.config.kernels, self.device, dtype)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)
        n, m = self.config.keepers, self.config.takers
        objects = 1 + n + m
        p = self.physics
        players = n + m

        def per_object(ball: float, player: float) -> Tensor:
            return torch.tensor([ball] + [player] * players, device=self.device, dtype=dtype)

        self.radius = per_object(p.ball_size, p.player_size)
        self.accel_max = per_object(p.ball_accel_max, p.player_accel_max)
        self.speed_max = per_object(p.ball_speed_max, p.player_speed_max)
        self.decay = per_object(p.ball_decay, p.player_decay)
        self.rand = per_object(p.ball_rand, p.player_rand)
        self.grid = get_open_grid(self.config.length, self.config.width, self.device, dtype)
        zeros = torch.zeros(batch_size, dtype=torch.long, device=self.device)
        self.server_perception = self.config.perception == "server"
        self.server_timing = self.config.decision_timing == "server"
        timed = players if self.config.sees else 0
        believers = players if self.server_perception else 0
        phase = (
            see_phases(batch_size, players, self.generator, self.device)
            if timed
            else torch.zeros(batch_size, 0, dtype=torch.long, device=self.device)
        )
        self.state = KeepawayState(
            pos=torch.zeros(batch_size, objects, 2, device=self.device, dtype=dtype),
            vel=torch.zeros(batch_size, objects, 2, device=self.device, dtype=dtype),
            body=torch.zeros(batch_size, objects, device=self.device, dtype=dtype),
            counter=zeros.clone(),
            episode_cycles=zeros.clone(),
            last_decision=torch.full((batch_size, n), -1, dtype=torch.long, device=self.device),
            prev_holder=zeros - 1,
            pass_target=zeros - 1,
            action_start=zeros.clone(),
            clock=zeros.clone(),
            see_phase=phase,
            seen_pos=torch.zeros(batch_size, believers, objects, 2, device=self.device, dtype=dtype),
            seen_vel=torch.zeros(batch_size, believers, objects, 2, device=self.device, dtype=dtype),
            seen_body=torch.zeros(batch_size, believers, objects, device=self.device, dtype=dtype),
            keepers=n,
            takers=m,
        )
        self.compiled = CompiledCycle(self.config, batch_size, seed) if self.kernels == "cycle" else None
        self.reset()

    def seed(self, seed: int) -> None:
        """Re-seed the simulator's generator (and the compiled path's per-field streams)."""
        self.generator.manual_seed(seed)
        if self.compiled is not None:
            self.compiled.reseed(seed)

    def state_dict(self) -> dict[str, object]:
        """Every field's play in progress (positions, world models, clocks...) and the generator: what
        :meth:`load_state_dict` continues exactly."""
        saved: dict[str, object] = {
            "state": {k: v.clone().cpu() for k, v in self.state.tensors().items()},
            "generator": self.generator.get_state(),
        }
        if self.compiled is not None:  # kernels="cycle": each field's own random stream
            saved["streams"] = torch.from_numpy(self.compiled.rng.copy())
        return saved

    def load_state_dict(self, state: dict[str, object]) -> None:
        """Continue the play of :meth:`state_dict` (same fields, players and perception)."""
        saved = state["state"]
        current = self.state.tensors()
        if not isinstance(saved, dict) or set(saved) != set(current):
            held = sorted(saved) if isinstance(saved, dict) else type(saved).__name__
            raise ValueError(f"keepaway simulator state holds {held}; expected {sorted(current)}")
        loaded = {}
        for k, now in current.items():
            v = saved[k]
            if not isinstance(v, Tensor) or v.shape != now.shape or v.dtype != now.dtype:
                raise ValueError(
                    f"keepaway simulator state {k!r}: {getattr(v, 'dtype', type(v).__name__)} "
                    f"{tuple(getattr(v, 'shape', ()))}; this simulator holds {now.dtype} {tuple(now.shape)}"
                )
            loaded[k] = v.to(self.device).clone()
        self.generator.set_state(state["generator"])
        if self.compiled is not None and "streams" in state:
            streams = state["streams"]
            if not isinstance(streams, Tensor) or tuple(streams.shape) != self.compiled.rng.shape:
                raise ValueError(
                    f"keepaway simulator streams: {tuple(getattr(streams, 'shape', ()))}; "
                    f"this simulator holds {self.compiled.rng.shape}"
                )
            self.compiled.rng[:] = streams.numpy()
        self.state = dataclasses.replace(self.state, **loaded)

    # ------------------------------------------------------------------ episode control

    def fresh_state(self) -> KeepawayState:
        """A new episode's state for every field (positions drawn, velocities zero, body
        angles kept from the current state)."""
        cfg = self.config
        keepers, takers, ball = reset_positions(
            self.batch_size,
            cfg.keepers,
            cfg.takers,
            cfg.length,
            cfg.width,
            self.generator,
            self.device,
            self.dtype,
        )
        s = self.state
        zeros = torch.zeros_like(s.counter)
        pos = torch.cat((ball.unsqueeze(1), keepers, takers), dim=1)
        vel = torch.zeros_like(s.vel)
        seen_pos, seen_vel, seen_body = s.seen_pos, s.seen_vel, s.seen_body
        if self.server_perception:  # everyone sees the reset state (the reference searches for <= 1 cycle)
            seen_pos, seen_vel, seen_body = observe(
                pos, vel, s.body, seen_pos, torch.zeros_like(seen_vel), seen_body, cfg.keepers, self.physics
            )
        return dataclasses.replace(
            s,
            pos=pos,
            vel=vel,
            body=s.body.clone(),
            seen_pos=seen_pos,
            seen_vel=seen_vel,
            seen_body=seen_body,
            counter=zeros,
            episode_cycles=zeros.clone(),
            last_decision=torch.full_like(s.last_decision, -1),
            prev_holder=zeros - 1,
            pass_target=zeros - 1,
            action_start=zeros.clone(),
        )

    def reset(self, mask: Tensor | None = None) -> None:
        """Start a new episode on the fields where ``mask`` [B] is true (all if ``None``).

        ``kernels="cycle"``: in place, per field in compiled code, drawn from each field's own random
        stream (the distribution of :meth:`fresh_state`), so a field's play does not depend on which
        other fields restart."""
        if self.compiled is not None:
            if mask is None:
                mask = torch.ones(self.batch_size, dtype=torch.bool)
            self.compiled.reset(self.state, mask.to(torch.bool).contiguous().numpy())
            return
        fresh = self.fresh_state()
        self.state = fresh if mask is None else fresh.where(mask.to(self.device), self.state)

    # ----------------------------------------------------------------------- observation

    def decision(self, state: KeepawayState | None = None) -> Decision:
        """Which fields' keeper with the ball must choose a macro-action now.

        The holder is the keeper closest to the ball. It must decide when it can kick the ball
        and is not in the middle of a macro-action: a pass runs on while the ball stays
        kickable, a HoldBall for ``decision_period_cycles`` cycles.
        """
        s = self.state if state is None else state
        dist = norm(s.keeper_pos - s.ball_pos.unsqueeze(1))
        nearest = dist.min(-1)
        holder = nearest.indices
        kickable = nearest.values <= self.physics.kickable_distance
        passing = s.pass_target >= 0
        if self.server_timing:
            if self.server_perception:  # KeepawayPlayer::keeper: WM->isBallKickable(), its own belief
                me = gather_points(s.keeper_pos, holder.unsqueeze(-1)).squeeze(1)
                believed = s.seen_pos[torch.arange(s.batch_size, device=self.device), holder, 0]
                kickable = norm(believed - me) < self.physics.kickable_distance
            sees = sees_now(s.clock, s.see_phase).gather(1, holder.unsqueeze(-1)).squeeze(-1)
            passing = passing & ~sees  # keeperWithBall re-decides at each see message
        holding = (s.pass_target < 0) & (
            s.episode_cycles - s.action_start < self.config.decision_period_cycles
        )
        running = (s.prev_holder == holder) & (passing | holding)
        return Decision(holder=holder, kickable=kickable, must_decide=kickable & ~running)

    def _seen_positions(self, decider: Tensor, s: KeepawayState) -> tuple[Tensor, Tensor]:
        """Keeper and taker positions as keeper ``decider`` perceives them."""
        keepers, takers = s.keeper_pos, s.taker_pos
        if self.server_perception:
            mine = s.seen_pos[torch.arange(s.batch_size, device=self.device), decider]  # [B, O, 2]
            return mine[:, 1 : 1 + s.keepers], mine[:, 1 + s.keepers :]
        if self.config.noisy_observations:
            me = gather_points(keepers, decider.unsqueeze(-1)).squeeze(1)
            my_body = s.body[:, 1:].gather(1, decider.unsqueeze(-1)).squeeze(-1)
            seen_keepers = quantised_view(me, my_body, keepers)
            idx = decider[:, None, None].expand(-1, 1, 2)
            keepers = seen_keepers.scatter(1, idx, me.unsqueeze(1))
            takers = quantised_view(me, my_body, takers)
        return keepers, takers

    def observe(self, decider: Tensor, state: KeepawayState | None = None) -> tuple[Tensor, Tensor]:
        """State variables [B, 4n + 2m - 3] of keeper ``decider`` [B] and its teammates by
        distance [B, n - 1]: from its world model under server perception, through the quantised
        sensor if ``noisy_observations``. ``kernels="cycle"`` computes them in compiled code, so that
        the teammate numbering is the one its cycle gives PassBall k (the two paths can order two
        teammates at the same seen distance differently)."""
        s = self.state if state is None else state
        if self.compiled is not None:
            return self.compiled.observations(s, decider)
        keepers, takers = self._seen_positions(decider, s)
        return keeper_state_variables(keepers, takers, decider)

    def episode_end_rewards(self, state: KeepawayState | None = None) -> Tensor:
        """Cycles since each keeper's last decision [B, n] (0 for keepers that never decided)."""
        s = self.state if state is None else state
        since = s.episode_cycles.unsqueeze(-1) - s.last_decision
        return torch.where(s.last_decision >= 0, since, torch.zeros_like(since))

    # ----------------------------------------------------------------------------- cycle

    def _uniforms(self, *shape: int) -> Tensor:
        return torch.rand(shape, generator=self.generator, device=self.device, dtype=self.dtype)

    def _commands(
        self,
        ppos: Tensor,
        pvel: Tensor,
        pbody: Tensor,
        ball: Tensor,
        ball_vel: Tensor,
        holder: Tensor,
        kickable: Tensor,
        pass_target: Tensor,
    ) -> Tensor:
        """Commands [B, P, 3] of every player acting on the true state: the keepers' and the takers'
        skills."""
        cfg, p = self.config, self.physics
        n = cfg.keepers
        traj = predict_ball(ball, ball_vel, p.ball_decay, cfg.intercept_horizon)
        rest = ball_rest_point(ball, ball_vel, p.ball_decay)
        cycles, points = intercept_estimate(
            ppos, pvel, pbody, ball, ball_vel, cfg.intercept_horizon, p, self.kernels
        )
        kcmd, with_ball = keeper_commands(
            ppos[:, :n],
            pvel[:, :n],
            pbody[:, :n],
            ppos[:, n:],
            pbody[:, n:],
            ball,
            ball_vel,
            traj,
            rest,
            cycles[:, :n],
            points[:, :n],
            holder,
            kickable,
            pass_target,
            self.grid,
            p,
            self.kernels,
            cfg.hold_ball,
        )
        tcmd = taker_commands(
            ppos[:, :n],
            pbody[:, :n],
            ppos[:, n:],
            pvel[:, n:],
            pbody[:, n:],
            ball,
            ball_vel,
            points[:, n:],
            with_ball,
            p,
            cfg.hold_ball,
        )
        return torch.cat((kcmd, tcmd), dim=1)

    def _commands_from_beliefs(
        self, s: KeepawayState, holder: Tensor, kickable: Tensor, pass_target: Tensor
    ) -> Tensor:
        """Commands [B, P, 3] with every player acting on its own world model (server perception):
        keepers' skills in one view per keeper, takers' in one view per taker."""
        cfg, p = self.config, self.physics
        n, m = cfg.keepers, cfg.takers
        batch, objects = s.batch_size, 1 + n + m
        horizon = cfg.intercept_horizon

        def views(first: int, count: int) -> tuple[Tensor, Tensor, Tensor]:
            shape = (batch * count, objects)
            return (
                s.seen_pos[:, first : first + count].reshape(*shape, 2),
                s.seen_vel[:, first : first + count].reshape(*shape, 2),
                s.seen_body[:, first : first + count].reshape(shape),
            )

        def diagonal(cmd: Tensor, count: int) -> Tensor:  # view k's command of player k: [B, count, 3]
            return torch.diagonal(cmd.view(batch, count, count, 3), dim1=1, dim2=2).transpose(1, 2)

        # keepers: each keeper's skills from its own view
        pos, vel, body = views(0, n)
        ball, ball_vel = pos[:, 0], vel[:, 0]
        kpos, kvel, kbody = pos[:, 1 : 1 + n], vel[:, 1 : 1 + n], body[:, 1 : 1 + n]
        cycles, points = intercept_estimate(kpos, kvel, kbody, ball, ball_vel, horizon, p, self.kernels)
        rep = functools.partial(torch.repeat_interleave, repeats=n, dim=0)
        kcmd, _ = keeper_commands(
            kpos,
            kvel,
            kbody,
            pos[:, 1 + n :],
            body[:, 1 + n :],
            ball,
            ball_vel,
            predict_ball(ball, ball_vel, p.ball_decay, horizon),
            ball_rest_point(ball, ball_vel, p.ball_decay),
            cycles,
            points,
            rep(holder),
            rep(kickable),
            rep(pass_target),
            self.grid,
            p,
            self.kernels,
            cfg.hold_ball,
        )
        # takers: each taker's skills from its own view (all players' look-ahead only for BlockPass)
        pos, vel, body = views(n, m)
        ball, ball_vel = pos[:, 0], vel[:, 0]
        searched = slice(1, objects) if m > 2 else slice(1 + n, objects)
        cycles, points = intercept_estimate(
            pos[:, searched], vel[:, searched], body[:, searched], ball, ball_vel, horizon, p, self.kernels
        )
        rep = functools.partial(torch.repeat_interleave, repeats=m, dim=0)
        with_ball = fastest_keeper(cycles[:, :n], rep(holder), rep(kickable)) if m > 2 else rep(holder)
        tcmd = taker_commands(
            pos[:, 1 : 1 + n],
            body[:, 1 : 1 + n],
            pos[:, 1 + n :],
            vel[:, 1 + n :],
            body[:, 1 + n :],
            ball,
            ball_vel,
            points[:, -m:],
            with_ball,
            p,
            cfg.hold_ball,
        )
        return torch.cat((diagonal(kcmd, n), diagonal(tcmd, m)), dim=1)

    def _updated_beliefs(
        self, s: KeepawayState, cmd: Tensor, pos: Tensor, vel: Tensor, body: Tensor, clock: Tensor
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Every player's world model after this cycle: extrapolated from its belief and its own
        command, then replaced by a see message of the new state where the player gets one."""
        p, n = self.physics, self.config.keepers
        kind, power, angle = cmd.unbind(-1)
        me_pos, me_body = s.pos[:, 1:], s.body[:, 1:]
        ball_seen, ball_vel_seen = s.seen_pos[:, :, 0], s.seen_vel[:, :, 0]
        kick = kind == KICK_KIND
        kicked = kick & (norm(ball_seen - me_pos) < p.kickable_distance)
        kick_power = torch.where(kick, power, torch.zeros_like(power))
        accel = kick_acceleration(me_pos, me_body, ball_seen, ball_vel_seen, kick_power, angle, p)
        pred = extrapolate(s.seen_pos, s.seen_vel, s.seen_body, accel, kicked, n, p)
        ball_pos, ball_vel = after_collision(
            *pred[:2], s.seen_pos, me_pos, s.vel[:, 1:], me_body, kind, power, vel[:, 1:], body[:, 1:], p
        )
        pred = (ball_pos, ball_vel, pred[2])
        sees = sees_now(clock, s.see_phase)
        if not bool(sees.any()):
            return own_truth(*pred, pos, vel, body)
        shape = s.seen_body.shape
        seen = observe(pos, vel, body, *pred, n, p, self._uniforms(*shape))
        pred = own_truth(*pred, pos, vel, body)
        return (
            torch.where(sees[..., None, None], seen[0], pred[0]),
            torch.where(sees[..., None, None], seen[1], pred[1]),
            torch.where(sees[..., None], seen[2], pred[2]),
        )

    def _restart_reward_clock(self, s: KeepawayState) -> KeepawayState:
        """Server decision timing: where the holder's pass carries on into this cycle (the ball still
        kickable), its last-decision cycle becomes this one (keeperWithBall's ``setLastAction`` on
        the follow-through), so the next reward counts from here."""
        dec = self.decision(s)
        carried = dec.kickable & (s.prev_holder == dec.holder) & (s.pass_target >= 0)
        h = dec.holder.unsqueeze(-1)
        now = torch.where(carried, s.episode_cycles, s.last_decision.gather(1, h).squeeze(-1))
        return dataclasses.replace(s, last_decision=s.last_decision.scatter(1, h, now.unsqueeze(-1)))

    def step(
        self, actions: Tensor | None = None, active: Tensor | None = None, auto_reset: bool = False
    ) -> CycleOutcome:
        """Advance the fields where ``active`` [B] is true by one cycle.

        :param actions: macro-actions [B] of the keepers that must decide now: 0 HoldBall,
            k >= 1 PassBall to the k-th nearest teammate; read only where ``decision()`` says
            ``must_decide`` (``None`` means HoldBall).
        :param auto_reset: start a new episode at once on fields whose episode ended.
        """
        cfg, p = self.config, self.physics
        s = self.state
        batch, n, m = self.batch_size, cfg.keepers, cfg.takers
        if active is None:
            active = torch.ones(batch, dtype=torch.bool, device=self.device)
        if self.compiled is not None:
            return self._step_compiled(actions, active, auto_reset)
        dec = self.decision(s)
        holder = dec.holder
        # record the new decisions
        if actions is None:
            actions = torch.zeros(batch, dtype=torch.long, device=self.device)
        order = teammate_order(self._seen_positions(holder, s)[0], holder)
        chosen = order.gather(1, (actions.clamp(1, n - 1) - 1).unsqueeze(-1)).squeeze(-1)
        new_target = torch.where(actions > 0, chosen, torch.full_like(chosen, -1))
        deciding = dec.must_decide & active
        pass_target = torch.where(deciding, new_target, s.pass_target)
        action_start = torch.where(deciding, s.episode_cycles, s.action_start)
        last_decision = s.last_decision.scatter(
            1,
            holder.unsqueeze(-1),
            torch.where(
                deciding, s.episode_cycles, s.last_decision.gather(1, holder.unsqueeze(-1)).squeeze(-1)
            ).unsqueeze(-1),
        )
        pass_target = torch.where(dec.kickable, pass_target, torch.full_like(pass_target, -1))

        # commands
        ball, ball_vel = s.ball_pos, s.ball_vel
        ppos, pvel, pbody = s.pos[:, 1:], s.vel[:, 1:], s.body[:, 1:]
        if self.server_perception:
            cmd = self._commands_from_beliefs(s, holder, dec.kickable, pass_target)
        else:
            cmd = self._commands(ppos, pvel, pbody, ball, ball_vel, holder, dec.kickable, pass_target)
        kind, power, angle = cmd.unbind(-1)

        # physics
        noisy = cfg.movement_noise
        kick_noise = self._uniforms(batch, n + m, 2) if noisy and p.kick_rand > 0 else None
        kicks = kick_acceleration(
            ppos,
            pbody,
            ball.unsqueeze(1),
            ball_vel.unsqueeze(1),
            torch.where(kind == KICK_KIND, power, torch.zeros_like(power)),
            angle,
            p,
            kick_noise,
        )
        dashes = dash_acceleration(pbody, torch.where(kind == DASH_KIND, power, torch.zeros_like(power)), p)
        speed = norm(pvel)
        turn_noise = self._uniforms(batch, n + m) if noisy else None
        turned = turn_body(pbody, angle, speed, p, turn_noise)
        new_body = torch.where(kind == TURN_KIND, turned, pbody)
        accel = torch.cat((kicks.sum(1, keepdim=True), dashes), dim=1)
        move_noise = self._uniforms(batch, 1 + n + m, 2) if noisy else None
        pos, vel = move(
            s.pos,
            s.vel,
            accel,
            self.accel_max,
            self.speed_max,
            self.decay,
            self.rand,
            p.polar_noise,
            move_noise,
        )
        pos, vel, _ = resolve_collisions(pos, vel, self.radius, cfg.collision_passes, kernels=self.kernels)

        # referee
        kd = p.kickable_distance
        counter = update_turnover_counter(s.counter, pos[:, 0], pos[:, 1 : 1 + n], pos[:, 1 + n :], kd)
        cause = end_cause(ball_in_region(pos[:, 0], cfg.length, cfg.width), counter, cfg.turnover)
        episode_cycles = s.episode_cycles + 1
        body = torch.cat((s.body[:, :1], new_body), dim=1)
        clock = s.clock + 1
        seen = (s.seen_pos, s.seen_vel, s.seen_body)
        if self.server_perception:
            seen = self._updated_beliefs(s, cmd, pos, vel, body, clock)
        new_state = dataclasses.replace(
            s,
            pos=pos,
            vel=vel,
            body=body,
            counter=counter,
            episode_cycles=episode_cycles,
            last_decision=last_decision,
            prev_holder=torch.where(dec.kickable, holder, torch.full_like(holder, -1)),
            pass_target=pass_target,
            action_start=action_start,
            clock=clock,
            seen_pos=seen[0],
            seen_vel=seen[1],
            seen_body=seen[2],
        )
        if self.server_timing:
            new_state = self._restart_reward_clock(new_state)
        self.state = new_state.where(active, s)
        ended = active & (cause != END_RUNNING)
        outcome = CycleOutcome(
            ended=ended,
            end_cause=torch.where(active, cause, torch.zeros_like(cause)),
            episode_cycles=self.state.episode_cycles,
            episode_end_rewards=self.episode_end_rewards(),
        )
        if auto_reset and bool(ended.any()):
            self.reset(ended)
        return outcome

    # ------------------------------------------------------------- whole cycles compiled

    def _torch_uniforms(self) -> np.ndarray:
        """The uniforms [B, U] one torch-path cycle draws from the generator, in its order (kick
        noise, turn noise, movement noise, withheld see information), laid out per field."""
        cfg, p, s = self.config, self.physics, self.state
        batch, players = self.batch_size, cfg.keepers + cfg.takers
        objects = players + 1
        parts = []
        if cfg.movement_noise:
            kick = self._uniforms(batch, players, 2) if p.kick_rand > 0 else torch.zeros(batch, players, 2)
            parts += [
                kick.reshape(batch, -1),
                self._uniforms(batch, players),
                self._uniforms(batch, objects, 2).reshape(batch, -1),
            ]
        if self.server_perception:
            sees = sees_now(s.clock + 1, s.see_phase)
            seen = (
                self._uniforms(batch, players, objects)
                if bool(sees.any())
                else torch.zeros(batch, players, objects)
            )
            parts.append(seen.reshape(batch, -1))
        if not parts:
            return np.zeros((batch, 1))
        return torch.cat(parts, dim=1).double().numpy()

    def _step_compiled(self, actions: Tensor | None, active: Tensor, auto_reset: bool) -> CycleOutcome:
        """:meth:`step` by the whole-cycle kernel on a copy of the state, with the torch path's draws."""
        if actions is None:
            actions = torch.zeros(self.batch_size, dtype=torch.long)
        uniforms = self._torch_uniforms()
        state = self.state.clone()
        cause = self.compiled.cycle(state, actions.long().contiguous(), active.contiguous(), uniforms)
        self.state = state
        ended = active & (cause != END_RUNNING)
        outcome = CycleOutcome(
            ended=ended,
            end_cause=cause,
            episode_cycles=state.episode_cycles.clone(),  # the compiled reset below works in place
            episode_end_rewards=self.episode_end_rewards(),
        )
        if auto_reset and bool(ended.any()):
            self.reset(ended)
        return outcome

    def advance(
        self,
        actions: Tensor | None,
        running: Tensor,
        *,
        sync: str = "all",
        first: bool = True,
        restart: bool = False,
        max_cycles: int = 100_000,
    ) -> Advance:
        """``kernels="cycle"``: advance the ``running`` fields to their next decision in one compiled
        call (SMDP steps). With ``first`` a first cycle applies ``actions`` (as :meth:`step`);
        ``sync="all"`` runs every field until its holder must decide or its episode ends (restarted
        and played on with ``restart``), ``sync="any"`` runs all in lock-step until one decides or
        ends. The state's tensors change in place; randomness comes from per-field streams."""
        compiled = self._require_compiled()
        if actions is None:
            actions = torch.zeros(self.batch_size, dtype=torch.long)
        running = running.contiguous()
        go = running.clone() if first else torch.zeros_like(running)
        return compiled.advance(
            self.state, actions.long().contiguous(), go, running, sync, restart, max_cycles
        )

    def play_policy(
        self, policy: str, episodes_per_field: int, max_cycles: int = 1 << 40
    ) -> tuple[Tensor, Tensor, Tensor, int]:
        """``kernels="cycle"``: benchmark keepers (``"hold"``, ``"random"``, ``"hand"``) deciding
        inside each cycle on every field until it has played ``episodes_per_field`` episodes (or
        ``max_cycles`` cycles), in one compiled call: durations [B, E] (cycles), end causes [B, E],
        episodes played [B] and the field-cycles simulated."""
        return self._require_compiled().play(self.state, policy, episodes_per_field, max_cycles)

    def _require_compiled(self) -> CompiledCycle:
        if self.compiled is None:
            raise ValueError(f"this call needs kernels='cycle', not kernels={self.config.kernels!r}")
        return self.compiled
