"""The keepaway referee (the server's keepaway mode): ball out of the region, the taker
possession counter, and the coach's reset of players and ball at the start of an episode.
"""

from __future__ import annotations

import torch
from torch import Tensor

from hfrl_torch.envs.keepaway.physics import norm

END_RUNNING = 0
END_OUT = 1
END_TAKEN = 2
CORNER_SPREAD = 3.0  # a keeper or taker starts up to this far inside its corner, per axis
BALL_START_INSET = 4.0  # the ball starts this far inside the bottom-left corner, per axis


def ball_in_region(ball_pos: Tensor, length: float, width: float) -> Tensor:
    """Whether the ball [..., 2] is strictly inside the L x W region centred on the origin."""
    return (ball_pos[..., 0].abs() < 0.5 * length) & (ball_pos[..., 1].abs() < 0.5 * width)


def update_turnover_counter(
    counter: Tensor, ball_pos: Tensor, keeper_pos: Tensor, taker_pos: Tensor, kickable_distance: float
) -> Tensor:
    """The possession counter after this cycle's movement.

    +1 if any taker is within the kickable distance of the ball (even if a keeper is too);
    reset to 0 if a keeper is and no taker is; unchanged if nobody is.
    """
    keeper_near = (norm(keeper_pos - ball_pos.unsqueeze(-2)) <= kickable_distance).any(-1)
    taker_near = (norm(taker_pos - ball_pos.unsqueeze(-2)) <= kickable_distance).any(-1)
    return torch.where(taker_near, counter + 1, torch.where(keeper_near, torch.zeros_like(counter), counter))


def end_cause(in_region: Tensor, counter: Tensor, turnover_cycles: int) -> Tensor:
    """Why each episode ended this cycle: 0 running, 1 ball out, 2 taken (out wins a tie)."""
    taken = counter >= turnover_cycles
    return torch.where(
        ~in_region,
        torch.full_like(counter, END_OUT),
        torch.where(taken, torch.full_like(counter, END_TAKEN), torch.full_like(counter, END_RUNNING)),
    )


def reset_positions(
    batch: int,
    keepers: int,
    takers: int,
    length: float,
    width: float,
    generator: torch.Generator,
    device: torch.device,
    dtype: torch.dtype = torch.float32,
) -> tuple[Tensor, Tensor, Tensor]:
    """Start positions drawn like the keepaway coach does.

    Keeper i takes slot (k0 + i) mod n for a random k0; slots 0, 1, 2 are the corners
    (-L/2 + U(0,3), -W/2 + U(0,3)), (L/2 - U(0,3), -W/2 + U(0,3)), (L/2 - U(0,3), W/2 - U(0,3));
    later slots are (U(-1,1), U(-1,1)). All takers start at (-L/2 + U(0,3), W/2 - U(0,3)); the
    ball at (-L/2 + 4, -W/2 + 4).

    :returns: keeper positions [B, n, 2], taker positions [B, m, 2], ball position [B, 2].
    """
    half = torch.tensor([0.5 * length, 0.5 * width], device=device, dtype=dtype)
    k0 = torch.randint(0, keepers, (batch,), generator=generator, device=device)
    u_keep = torch.rand((batch, keepers, 2), generator=generator, device=device, dtype=dtype)
    u_take = torch.rand((batch, takers, 2), generator=generator, device=device, dtype=dtype)
    corner_sign = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [1.0, 1.0]], device=device, dtype=dtype)
    slot = (k0.unsqueeze(-1) + torch.arange(keepers, device=device)) % keepers  # [B, n]
    corner = corner_sign[slot.clamp(max=2)]  # [B, n, 2]
    corner_pos = corner * (half - CORNER_SPREAD * u_keep)
    centre_pos = 2.0 * u_keep - 1.0
    keeper_pos = torch.where((slot < 3).unsqueeze(-1), corner_pos, centre_pos)
    taker_corner = torch.tensor([-1.0, 1.0], device=device, dtype=dtype)
    taker_pos = taker_corner * (half - CORNER_SPREAD * u_take)
    ball_pos = (-half + BALL_START_INSET).expand(batch, 2).clone()
    return keeper_pos, taker_pos, ball_pos
