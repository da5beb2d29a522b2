"""rgb_array frames for kinetix.gym: the level drawn by kinetix.draw, the browser's renderer, without its text."""

from __future__ import annotations

import jax
import numpy as np

from kinetix.draw import View, level_frame

RENDER_MODES = ["rgb_array"]
DEFAULT_RENDER_SIZE = 512  # pixels: the browser's default canvas (kinetix.draw.View)


def check_render(render_mode: str | None, render_size: int) -> None:
    if render_mode is not None and render_mode not in RENDER_MODES:
        raise ValueError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")
    if isinstance(render_size, bool) or not isinstance(render_size, int) or not 16 <= render_size <= 4096:
        raise ValueError(f"render_size must be an integer number of pixels in [16, 4096], got {render_size!r}")


def frames(levels, indices, size: int) -> tuple[np.ndarray, ...]:
    """(size, size, 3) uint8 frames of the host levels (numpy leaves, leading axis) at `indices`."""
    view = View(size, size)
    return tuple(level_frame(jax.tree.map(lambda x: x[i], levels), view) for i in indices)


def render_fps(batch) -> int:
    """Frames per second of real time: one frame per agent step of frame_skip physics steps of dt seconds."""
    dt = float(np.asarray(batch.params.sim.dt))
    return max(1, round(1.0 / (dt * batch.env.config.frame_skip)))
