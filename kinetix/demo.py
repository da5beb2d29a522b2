"""Stand-in for `kinetix serve` until the web server exists: play a project level and write a GIF.

Runs every level in levels/ for a few seconds with a simple scripted policy (all motors
forward, thrusters pulsing), renders frames with the JAX pixel renderer and writes an
animated GIF per level, so a fresh checkout shows the engine and environment working.
"""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

LEVELS = Path(__file__).resolve().parents[1] / "levels"


def main(out_dir: str = "demo-output", seconds: float = 4.0, resolution: int = 192) -> int:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from PIL import Image

    import jax2d
    from kinetix.bindings import expand_actions
    from kinetix.levels import load_level
    from kinetix.render import render_pixels, to_uint8

    files = sorted(LEVELS.glob("*.json"))
    if not files:
        print(f"no levels in {LEVELS}", file=sys.stderr)
        return 1
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    frames_per_second, physics_per_frame = 30, 2
    n_frames = int(seconds * frames_per_second)

    def advance(carry, t):
        level, params = carry
        pulse = (t // 20) % 2  # thrusters on for 20 frames, off for 20
        m, th = expand_actions(level, jnp.ones(4), jnp.full(2, pulse, jnp.float32))
        for _ in range(physics_per_frame):
            level = dataclasses.replace(level, sim=jax2d.step(level.sim, params, m, th))
        return (level, params), render_pixels(level, resolution)

    # One compiled program per size class: levels and params are arguments, not constants.
    play = jax2d.jit(lambda level, params: jax.lax.scan(advance, (level, params), jnp.arange(n_frames))[1])
    for path in files:
        lf = load_level(path)
        frames = play(lf.level, lf.params.sim_params())
        images = [Image.fromarray(np.asarray(to_uint8(f))) for f in frames]
        target = out / f"{path.stem}.gif"
        images[0].save(target, save_all=True, append_images=images[1:], duration=1000 // frames_per_second, loop=0)
        print(f"wrote {target}")
    print(f"The web editor is not built yet; the demo GIFs are in {out.resolve()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
