"""Pictures of a keepaway field (numpy + Pillow only): a frame as an RGB array and episodes
as animated GIFs."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import Image, ImageDraw

from hfrl_torch.envs.keepaway.params import KeepawayConfig
from hfrl_torch.envs.keepaway.simulator import KeepawaySimulator, KeepawayState

GRASS = (34, 110, 52)
LINES = (235, 235, 235)
KEEPER = (40, 90, 230)
TAKER = (220, 40, 40)
BALL = (255, 255, 255)
HOLDER = (255, 215, 0)


def render_rgb(
    state: KeepawayState,
    field_index: int = 0,
    config: KeepawayConfig | None = None,
    pixels_per_metre: float = 16.0,
    margin: float = 2.0,
) -> np.ndarray:
    """Field ``field_index`` of ``state`` as an image [H, W, 3] uint8: the region, keepers
    (blue), takers (red), the ball (white) and the keeper closest to the ball ringed in gold
    when it can kick the ball. ``config`` gives the region (default 20 x 20 m)."""
    config = config if config is not None else KeepawayConfig(keepers=state.keepers, takers=state.takers)
    length, width = config.length, config.width
    size = (int((length + 2 * margin) * pixels_per_metre), int((width + 2 * margin) * pixels_per_metre))
    image = Image.new("RGB", size, GRASS)
    draw = ImageDraw.Draw(image)

    def to_px(x: float, y: float) -> tuple[float, float]:
        return ((x + 0.5 * length + margin) * pixels_per_metre, (0.5 * width + margin - y) * pixels_per_metre)

    x0, y0 = to_px(-0.5 * length, 0.5 * width)
    x1, y1 = to_px(0.5 * length, -0.5 * width)
    draw.rectangle((x0, y0, x1, y1), outline=LINES, width=2)
    pos = state.pos[field_index].detach().cpu().double().numpy()
    body = state.body[field_index].detach().cpu().double().numpy()
    n = state.keepers
    ball = pos[0]
    keeper_dist = np.hypot(*(pos[1 : 1 + n] - ball).T)
    holder = int(np.argmin(keeper_dist))
    kickable = keeper_dist[holder] <= config.physics.kickable_distance
    radius = max(3.0, 0.5 * pixels_per_metre)
    for i, (x, y) in enumerate(pos[1:]):
        cx, cy = to_px(x, y)
        colour = KEEPER if i < n else TAKER
        if i == holder and kickable:
            r = radius + 3
            draw.ellipse((cx - r, cy - r, cx + r, cy + r), fill=HOLDER)
        draw.ellipse((cx - radius, cy - radius, cx + radius, cy + radius), fill=colour)
        hx, hy = np.cos(body[i + 1]), np.sin(body[i + 1])
        draw.line((cx, cy, cx + hx * radius * 1.6, cy - hy * radius * 1.6), fill=LINES, width=2)
    bx, by = to_px(*ball)
    br = max(2.0, 0.25 * pixels_per_metre)
    draw.ellipse((bx - br, by - br, bx + br, by + br), fill=BALL, outline=(0, 0, 0))
    return np.asarray(image, dtype=np.uint8)


def write_gif(frames: Sequence[np.ndarray], path: str | Path, fps: int = 10) -> Path:
    """Write RGB frames [H, W, 3] uint8 as an endlessly looping GIF."""
    if not frames:
        raise ValueError("no frames to write")
    path = Path(path)
    images = [Image.fromarray(frame) for frame in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return path


def record_episode_gif(
    path: str | Path,
    policy: Callable[[torch.Tensor], torch.Tensor],
    config: KeepawayConfig | None = None,
    seed: int = 0,
    max_cycles: int = 600,
    fps: int = 10,
) -> tuple[Path, int]:
    """Play one episode with keeper ``policy`` (state variables -> actions) and save it as a
    GIF; returns the path and the episode length in cycles."""
    sim = KeepawaySimulator(1, config, seed=seed)
    frames = [render_rgb(sim.state, 0, sim.config)]
    cycles = 0
    for _ in range(max_cycles):
        holder = sim.decision().holder
        obs, _ = sim.observe(holder)
        out = sim.step(policy(obs))
        frames.append(render_rgb(sim.state, 0, sim.config))
        cycles = int(out.episode_cycles[0])
        if bool(out.ended[0]):
            break
    return write_gif(frames, path, fps), cycles
