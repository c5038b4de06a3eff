"""The batched keepaway simulator: B independent fields advanced in lock-step, one 100 ms
cycle per call, with the keepers' and takers' skills built in. Only the choice of the keeper
with the ball (HoldBall or PassBall(k)) comes from outside.

Layer: engine. No TorchRL here; env.py wraps this in an EnvBase.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.keepers import keeper_commands
from hfrl_torch.envs.keepaway.params import KeepawayConfig, resolve_kernels
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
        return dataclasses.replace(self, **{k: v.clone() for k, v in self.tensors().items()})

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
            keepers=n,
            takers=m,
        )
        self.reset()

    def seed(self, seed: int) -> None:
        """Re-seed the simulator's generator."""
        self.generator.manual_seed(seed)

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
        return dataclasses.replace(
            s,
            pos=torch.cat((ball.unsqueeze(1), keepers, takers), dim=1),
            vel=torch.zeros_like(s.vel),
            body=s.body.clone(),
            counter=zeros,
            episode_cycles=zeros.clone(),
            last_decision=torch.full_like(s.last_decision, -1),
            prev_holder=zeros - 1,
            pass_target=zeros - 1,
            action_start=zeros.clone(),
        )

    def reset(self, mask: Tensor | None = None) -> None:
        """Start a new episode on the fields where ``mask`` [B] is true (all if ``None``)."""
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
        running = (s.prev_holder == holder) & (
            (s.pass_target >= 0) | (s.episode_cycles - s.action_start < self.config.decision_period_cycles)
        )
        return Decision(holder=holder, kickable=kickable, must_decide=kickable & ~running)

    def _seen_positions(self, decider: Tensor, s: KeepawayState) -> tuple[Tensor, Tensor]:
        """Keeper and taker positions as keeper ``decider`` perceives them."""
        keepers, takers = s.keeper_pos, s.taker_pos
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
        distance [B, n - 1]; through the quantised sensor if ``noisy_observations``."""
        s = self.state if state is None else state
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
            dec.kickable,
            pass_target,
            self.grid,
            p,
            self.kernels,
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
        )
        cmd = torch.cat((kcmd, tcmd), dim=1)  # [B, P, 3]
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
        new_state = dataclasses.replace(
            s,
            pos=pos,
            vel=vel,
            body=torch.cat((s.body[:, :1], new_body), dim=1),
            counter=counter,
            episode_cycles=episode_cycles,
            last_decision=last_decision,
            prev_holder=torch.where(dec.kickable, holder, torch.full_like(holder, -1)),
            pass_target=pass_target,
            action_start=action_start,
        )
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
