"""One simulator cycle of rcssserver physics, batched over fields: kicks, dashes, turns,
movement with noise, and collision resolution.

All functions are pure tensor functions over arbitrary leading batch dimensions; angles are
radians. Nothing here knows about teams or skills (see skills.py) or about the referee.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.params import PhysicsParams, resolve_kernels

TURN_KIND = 1
DASH_KIND = 2
KICK_KIND = 3
COLLISION_BOUNCE = -0.1  # the factor on a collided object's velocity
COLLISION_SLACK = 1e-6  # the push apart beyond touching


def wrap_angle(angle: Tensor) -> Tensor:
    """Angle mapped into [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2.0 * math.pi) - math.pi


def unit(angle: Tensor) -> Tensor:
    """Unit vectors [..., 2] pointing along ``angle``."""
    return torch.stack((torch.cos(angle), torch.sin(angle)), dim=-1)


def _components(vec: Tensor) -> tuple[Tensor, Tensor]:
    """x and y of vectors [..., 2], contiguous on CPU (strided inputs miss torch's vectorised
    atan2 and hypot there, several times slower)."""
    x, y = vec[..., 0], vec[..., 1]
    return (x.contiguous(), y.contiguous()) if vec.device.type == "cpu" else (x, y)


def direction(vec: Tensor) -> Tensor:
    """Angle of vectors [..., 2]."""
    x, y = _components(vec)
    return torch.atan2(y, x)


def norm(vec: Tensor) -> Tensor:
    """Euclidean length of vectors [..., 2]."""
    x, y = _components(vec)
    return torch.hypot(x, y)


def hypot_f64(x: Tensor, y: Tensor) -> Tensor:
    """sqrt(x^2 + y^2) in float64, rounded once to the inputs' dtype: the numba kernels' hypot,
    so that both paths agree to the bit (torch's own hypot is correctly rounded in its
    vectorised loop only, and this one is not quite correctly rounded)."""
    x64, y64 = x.double(), y.double()
    return torch.sqrt(x64 * x64 + y64 * y64).to(x.dtype)


def dot(a: Tensor, b: Tensor) -> Tensor:
    """Dot product over the last dimension."""
    return (a * b).sum(-1)


def clip_norm(vec: Tensor, max_norm: Tensor | float) -> Tensor:
    """Vectors scaled down so their length is at most ``max_norm``."""
    length = norm(vec)
    scale = torch.clamp(
        torch.as_tensor(max_norm, dtype=vec.dtype, device=vec.device) / length.clamp_min(1e-12), max=1.0
    )
    return vec * scale.unsqueeze(-1)


def kick_power_rate(
    kicker_pos: Tensor, kicker_body: Tensor, ball_pos: Tensor, physics: PhysicsParams
) -> Tensor:
    """Ball acceleration per unit of kick power (the server's effective kick power rate).

    Falls linearly with the ball's angle off the body (-25 % at the back) and with the gap
    between ball and body (-25 % at the edge of the kickable area).
    """
    rel = ball_pos - kicker_pos
    dir_diff = wrap_angle(direction(rel) - kicker_body).abs()
    gap = norm(rel) - physics.player_size - physics.ball_size
    return physics.kick_power_rate * (1.0 - 0.25 * dir_diff / math.pi - 0.25 * gap / physics.kickable_margin)


def kick_acceleration(
    kicker_pos: Tensor,
    kicker_body: Tensor,
    ball_pos: Tensor,
    ball_vel: Tensor,
    power: Tensor,
    kick_dir: Tensor,
    physics: PhysicsParams,
    noise: Tensor | None = None,
) -> Tensor:
    """Acceleration [..., 2] a kick gives the ball; zero when the ball is out of kickable range.

    :param kick_dir: kick direction relative to the kicker's body.
    :param noise: two uniforms in [0, 1) per kick [..., 2] for the rcss19 kick noise
        (radius and angle); ``None`` or ``kick_rand == 0`` means no kick noise.
    """
    rel = ball_pos - kicker_pos
    dist = norm(rel)
    power = power.clamp(0.0, physics.max_power)
    rate = kick_power_rate(kicker_pos, kicker_body, ball_pos, physics)
    accel = (power * rate).unsqueeze(-1) * unit(kicker_body + kick_dir)
    if noise is not None and physics.kick_rand > 0:
        dir_diff = wrap_angle(direction(rel) - kicker_body).abs()
        gap = dist - physics.player_size - physics.ball_size
        max_rand = (
            physics.kick_rand
            * (power / physics.max_power)
            * (
                (0.5 + 0.25 * (dir_diff / math.pi + gap / physics.kickable_margin))
                + (0.5 + 0.5 * norm(ball_vel) / (physics.ball_speed_max * physics.ball_decay))
            )
        )
        radius = noise[..., 0] * max_rand
        accel = accel + radius.unsqueeze(-1) * unit((2.0 * noise[..., 1] - 1.0) * math.pi)
    kickable = dist <= physics.kickable_distance
    return accel * kickable.unsqueeze(-1)


def dash_acceleration(body: Tensor, power: Tensor, physics: PhysicsParams) -> Tensor:
    """Acceleration [..., 2] of a dash with ``power`` along the body (stamina never limits)."""
    power = power.clamp(physics.min_dash_power, physics.max_power)
    return (power * physics.dash_power_rate).unsqueeze(-1) * unit(body)


def turn_body(
    body: Tensor, moment: Tensor, speed: Tensor, physics: PhysicsParams, noise: Tensor | None = None
) -> Tensor:
    """Body angle after a turn of ``moment``, reduced by the inertia of a moving player.

    :param noise: uniforms in [0, 1) scaling the turn by 1 + U(-player_rand, player_rand).
    """
    moment = moment.clamp(-physics.max_moment, physics.max_moment)
    actual = moment / (1.0 + physics.inertia_moment * speed)
    if noise is not None:
        actual = actual * (1.0 + physics.player_rand * (2.0 * noise - 1.0))
    return wrap_angle(body + actual)


def movement_noise(vel: Tensor, rand: Tensor, uniforms: Tensor, polar: bool) -> Tensor:
    """Server movement noise for velocities [..., 2] with magnitude scale ``rand * |v|``.

    Server 9 draws each axis from U(-r|v|, r|v|); rcss19 draws a polar vector with radius
    U(0, r|v|) and a uniform angle. ``uniforms`` holds two U(0, 1) numbers per object [..., 2].
    """
    scale = rand * norm(vel)
    if polar:
        radius = uniforms[..., 0] * scale
        return radius.unsqueeze(-1) * unit((2.0 * uniforms[..., 1] - 1.0) * math.pi)
    return (2.0 * uniforms - 1.0) * scale.unsqueeze(-1)


def move(
    pos: Tensor,
    vel: Tensor,
    accel: Tensor,
    accel_max: Tensor,
    speed_max: Tensor,
    decay: Tensor,
    rand: Tensor,
    polar_noise: bool,
    noise_uniforms: Tensor | None = None,
) -> tuple[Tensor, Tensor]:
    """Advance objects one cycle: cap the acceleration, accelerate, cap the speed, add noise,
    move, decay. Per-object constants broadcast against [..., O].

    :returns: the new positions and the new (decayed) velocities.
    """
    accel = clip_norm(accel, accel_max)
    vel = clip_norm(vel + accel, speed_max)
    if noise_uniforms is not None:
        vel = vel + movement_noise(vel, rand, noise_uniforms, polar_noise)
    pos = pos + vel
    return pos, vel * decay.unsqueeze(-1)


def resolve_collisions(
    pos: Tensor,
    vel: Tensor,
    radius: Tensor,
    max_passes: int = 10,
    slack: float = COLLISION_SLACK,
    kernels: str = "auto",
) -> tuple[Tensor, Tensor, Tensor]:
    """Push overlapping objects apart until they touch, then reverse the collided velocities.

    Like the server, pairs are handled one after the other (vectorised over fields): an
    overlapping pair moves apart along its centre line, each member half the overlap (plus
    ``slack``), so later pairs see the moved positions. Passes over all pairs repeat while any
    pair overlaps, at most ``max_passes`` times. Two objects at the same point separate along a
    fixed direction per pair. Every object that collided gets v = -0.1 v, once.

    :param pos: positions [B, O, 2].
    :param vel: velocities [B, O, 2].
    :param radius: object radii [O].
    :param kernels: ``"numba"`` (a compiled loop per field), ``"torch"`` or ``"auto"``; the same bits.
    :returns: new positions, new velocities, and which objects collided [B, O].
    """
    num = pos.shape[-2]
    if radius.shape != (num,):
        raise ValueError(f"radius has shape {tuple(radius.shape)}; expected ({num},), one per object")
    if resolve_kernels(kernels, pos.device, pos.dtype) == "numba":
        from hfrl_torch.envs.keepaway.kernels_numba import push_apart

        pairs, contact, check, fallback = _pair_constants(tuple(radius.tolist()))
        new_pos = pos.reshape(-1, num, 2).clone()
        collided = torch.empty(new_pos.shape[:2], dtype=torch.bool)
        consts = torch.tensor([slack, 1e-9, 0.5, 1.0], dtype=torch.float32)
        push_apart(
            new_pos.numpy(),
            pairs.numpy(),
            contact.numpy(),
            check.numpy(),
            fallback.numpy(),
            max_passes,
            consts.numpy(),
            collided.numpy(),
        )
        collided = collided.reshape(pos.shape[:-1])
        vel = torch.where(collided.unsqueeze(-1), COLLISION_BOUNCE * vel, vel)
        return new_pos.reshape(pos.shape), vel, collided
    pairs = torch.triu_indices(num, num, offset=1).T.tolist()
    radii = radius.tolist()
    xs = list(pos[..., 0].unbind(-1))
    ys = list(pos[..., 1].unbind(-1))
    hit = [torch.zeros(pos.shape[:-2], dtype=torch.bool, device=pos.device) for _ in range(num)]
    first, second = torch.triu_indices(num, num, offset=1, device=pos.device)
    contacts = radius[first] + radius[second]
    for _ in range(max_passes):
        x_all, y_all = torch.stack(xs, -1), torch.stack(ys, -1)
        gap = hypot_f64(
            x_all.index_select(1, second) - x_all.index_select(1, first),
            y_all.index_select(1, second) - y_all.index_select(1, first),
        )
        if not bool((gap < contacts).any()):
            break
        for k, (i, j) in enumerate(pairs):
            contact = radii[i] + radii[j]
            dx, dy = xs[j] - xs[i], ys[j] - ys[i]
            dist = hypot_f64(dx, dy)
            overlap = dist < contact
            safe = dist > 1e-9
            inv = 1.0 / dist.clamp_min(1e-9)
            angle = k * PAIR_FALLBACK_STEP
            ax = torch.where(safe, dx * inv, math.cos(angle))
            ay = torch.where(safe, dy * inv, math.sin(angle))
            push = 0.5 * (contact - dist) + slack
            xs[i], xs[j] = (
                torch.where(overlap, xs[i] - push * ax, xs[i]),
                torch.where(overlap, xs[j] + push * ax, xs[j]),
            )
            ys[i], ys[j] = (
                torch.where(overlap, ys[i] - push * ay, ys[i]),
                torch.where(overlap, ys[j] + push * ay, ys[j]),
            )
            hit[i] = hit[i] | overlap
            hit[j] = hit[j] | overlap
    collided = torch.stack(hit, -1)
    vel = torch.where(collided.unsqueeze(-1), COLLISION_BOUNCE * vel, vel)
    return torch.stack((torch.stack(xs, -1), torch.stack(ys, -1)), -1), vel, collided


PAIR_FALLBACK_STEP = 2.399963229728653  # golden angle: pair k at one point separates along k times it


@functools.lru_cache(maxsize=8)
def _pair_constants(radii: tuple[float, ...]) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Per pair (torch order) of :func:`resolve_collisions`: indices [K, 2], the contact distance
    as the push computes it (summed in float64) and as the pass test does (in float32), and the
    fallback direction [K, 2]."""
    num = len(radii)
    pairs = torch.triu_indices(num, num, offset=1).T.contiguous()
    radius = torch.tensor(radii, dtype=torch.float32)
    contact = torch.tensor([radii[i] + radii[j] for i, j in pairs.tolist()], dtype=torch.float32)
    check = radius[pairs[:, 0]] + radius[pairs[:, 1]]
    angles = [k * PAIR_FALLBACK_STEP for k in range(len(pairs))]
    fallback = torch.tensor([[math.cos(a), math.sin(a)] for a in angles], dtype=torch.float32)
    return pairs, contact, check, fallback
