"""Heavy-on-light stacks (issue 35, "Mass ratios"): how far boxes sink into each other and into the floor.

    python -m tests.jax2d.mass_ratio          # the table of every variation (docs/engine.md, "Accuracy")

A stack is a column of 2 or 3 boxes resting on a floor, listed bottom to top, each its own width, height and
mass, optionally shifted sideways. The floor is either the accuracy scene's static 40 m slab (its top at
y = 0) or the levels' four standard walls (kinetix.level.add_walls: the floor's top at y = 0.4), solved with
the plain SolverConfig() or the walls solver (num_static = 4, kinetix.level.WALLS_SOLVER). Every variation
of one floor and config runs in one batch (one compile). The overlaps are measured from the recorded poses by
the separating-axis test (exact for convex polygons, whatever the boxes' tilt): between each box and the one
below it, and between the bottom box and the floor, at the end and the largest over the run.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools

import jax
import numpy as np

import jax2d
from jax2d import scene
from tests.jax2d.scenes import stack

DT = 1.0 / 60.0
CAPACITY = jax2d.Capacity(polygons=7, circles=0, joints=0, thrusters=0, max_vertices=4)
DEFAULT_CONFIG = jax2d.SolverConfig()


@dataclasses.dataclass(frozen=True)
class Stack:
    """Boxes bottom to top: sizes ((width, height), ...) in m, masses in kg, sideways offsets of each box's
    centre from the column's axis in m."""

    sizes: tuple
    masses: tuple
    offsets: tuple = ()

    def __post_init__(self):
        if len(self.sizes) != len(self.masses) or not 2 <= len(self.sizes) <= 3:
            raise ValueError("a stack is 2 or 3 boxes, with one size and one mass each")
        if self.offsets and len(self.offsets) != len(self.sizes):
            raise ValueError("give one sideways offset per box, or none")

    @property
    def label(self) -> str:
        def size(s):
            return f"{s[0]:g}" if s[0] == s[1] else f"{s[0]:g}x{s[1]:g}"

        text = ":".join(f"{m:g}" for m in self.masses) + " kg, " + "/".join(size(s) for s in self.sizes) + " m"
        if any(self.offsets):
            text += ", offsets " + "/".join(f"{o * 1000:g}" for o in self.offsets) + " mm"
        return text


def add_slab(state: jax2d.SimState) -> tuple[jax2d.SimState, int, tuple[float, float]]:
    """The accuracy scene's floor: a static 40 m x 1 m slab, its top at y = 0. Returns the state, the floor's
    body index and where the column stands (x, floor top)."""
    state, floor = scene.add_rectangle(state, (0.0, -0.5), 40.0, 1.0, fixed=True)
    return state, floor, (0.0, 0.0)


def build(spec: Stack, add_floor=add_slab) -> tuple[jax2d.SimState, int, list[int]]:
    """The stack's scene on the floor that `add_floor` adds (see add_slab); returns it, the floor's index and the
    boxes' indices, bottom to top."""
    state, floor, (x0, y) = add_floor(jax2d.empty_state(CAPACITY))
    offsets = spec.offsets or (0.0,) * len(spec.sizes)
    boxes = []
    for (w, h), mass, dx in zip(spec.sizes, spec.masses, offsets, strict=True):
        state, i = scene.add_rectangle(state, (x0 + dx, y + h / 2), w, h, density=mass / (w * h))
        boxes.append(i)
        y += h
    return state, floor, boxes


@functools.partial(jax2d.jit, static_argnames=("steps", "config"))
def _rollout(states, params, steps: int, config: jax2d.SolverConfig):
    motors = np.zeros((0,), np.float32)
    thrusts = np.zeros((0,), np.float32)
    one = jax.vmap(lambda s: jax2d.step(s, params, motors, thrusts, config=config))

    def body(s, _):
        s = one(s)
        return s, (s.bodies.position, s.bodies.angle)

    final, (position, angle) = jax.lax.scan(body, states, None, length=steps)
    return final, position, angle


def _world_vertices(vertices, n_vertices, position, angle):
    """(..., V, 2) world vertices of one polygon over a trajectory (padding repeats the last vertex)."""
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    v = vertices[:n_vertices]
    x = c * v[:, 0] - s * v[:, 1] + position[..., None, 0]
    y = s * v[:, 0] + c * v[:, 1] + position[..., None, 1]
    return np.stack([x, y], axis=-1)


def overlap(pa: np.ndarray, pb: np.ndarray) -> np.ndarray:
    """Penetration depth (m, > 0 when overlapping) of convex counter-clockwise polygons (..., Va, 2) and
    (..., Vb, 2): the smallest push along any edge normal of either that separates them."""
    def deepest(p, q):  # the largest separation of q from p's edges
        edges = np.roll(p, -1, axis=-2) - p
        normals = np.stack([edges[..., 1], -edges[..., 0]], axis=-1)
        normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
        # separation of q from edge i: min over q's vertices of n_i . (q_j - p_i)
        d = np.einsum("...ik,...jk->...ij", normals, q) - np.einsum("...ik,...ik->...i", normals, p)[..., None]
        return d.min(axis=-1).max(axis=-1)

    return -np.maximum(deepest(pa, pb), deepest(pb, pa))


def measure(specs: list[Stack], seconds: float = 5.0, params: jax2d.SimParams | None = None,
            config: jax2d.SolverConfig = DEFAULT_CONFIG, add_floor=add_slab, checkpoints: tuple = ()) -> list[dict]:
    """Step every stack for `seconds` in one batch (one compile); per stack its overlaps (m): `between` (each box
    with the one below, bottom pair first) and `floor` at the end, `worst_between` / `worst_floor` the largest
    over the run, `end` and `sink` the largest of those at the end and over the run, `at` the largest at each
    of `checkpoints` (s), `x_drift` (the boxes' largest sideways move) and `frozen` (bodies the step's guard
    froze)."""
    params = params or jax2d.SimParams()
    built = [build(s, add_floor) for s in specs]
    states = stack([b[0] for b in built])
    x0 = float(states.bodies.position[0, built[0][2][0], 0]) - (specs[0].offsets or (0.0,))[0]
    final, position, angle = _rollout(states, params, round(seconds / DT), config)
    position, angle = np.asarray(position, np.float64), np.asarray(angle, np.float64)
    frozen = np.asarray(final.frozen)
    results = []
    for k, (spec, (_, floor_index, boxes)) in enumerate(zip(specs, built, strict=True)):
        def poly(i, k=k):
            verts = np.asarray(states.bodies.vertices[k, i], np.float64)
            return _world_vertices(verts, int(states.bodies.n_vertices[k, i]), position[:, k, i], angle[:, k, i])

        shapes = [poly(i) for i in boxes]
        between = np.stack([overlap(lo, hi) for lo, hi in itertools.pairwise(shapes)])  # (pairs, steps)
        floor = overlap(poly(floor_index), shapes[0])
        drift = np.abs(position[-1, k, boxes, 0] - x0 - np.asarray(spec.offsets or 0.0)).max()
        results.append(dict(between=between[:, -1].tolist(), floor=float(floor[-1]),
                            worst_between=between.max(axis=1).tolist(), worst_floor=float(floor.max()),
                            end=float(max(between[:, -1].max(), floor[-1])),
                            at=[float(max(between[:, round(t / DT) - 1].max(), floor[round(t / DT) - 1]))
                                for t in checkpoints],
                            sink=float(max(between.max(), floor.max())), x_drift=float(drift), frozen=int(frozen[k])))
    return results


def variations() -> list[Stack]:
    """The stacks a reviewer would try (issue 35, "Mass ratios"): 100:1 at three absolute masses on square boxes of
    0.1, 0.5 and 1 m; the light box wider or narrower than the heavy one; the heavy box a little off the light
    one's middle; three-box stacks, 100 on 10 on 1 and 100 on 1 on 1 kg. The tests hold every one of them within
    2 slops over a 10 s run (test_mass_ratio.py, tests/kinetix/test_mass_ratio_walls.py)."""
    specs = []
    for light, heavy in ((0.1, 10.0), (1.0, 100.0), (10.0, 1000.0)):
        for side in (0.1, 0.5, 1.0):
            specs.append(Stack(((side, side), (side, side)), (light, heavy)))
    for lo, hi in ((1.0, 0.5), (0.5, 1.0), (0.25, 0.5), (0.5, 0.25)):
        specs.append(Stack(((lo, lo), (hi, hi)), (1.0, 100.0)))
    for offset in (0.02, -0.05):
        specs.append(Stack(((0.5, 0.5), (0.5, 0.5)), (1.0, 100.0), (0.0, offset)))
    specs.append(Stack(((0.5, 0.5),) * 3, (1.0, 10.0, 100.0)))
    specs.append(Stack(((0.5, 0.5),) * 3, (1.0, 1.0, 100.0)))
    specs.append(Stack(((0.3, 0.3),) * 3, (0.1, 1.0, 10.0), (0.0, 0.02, -0.02)))
    return specs


def extremes() -> list[Stack]:
    """Stacks beyond those (docs/engine.md, "Known problems"): a 10:1 size ratio either way, a flat or a tall
    light box, the heavy box far off the light one's middle, and a light stack on a heavy box."""
    specs = [Stack(((lo, lo), (hi, hi)), (1.0, 100.0)) for lo, hi in ((0.1, 1.0), (1.0, 0.1))]
    specs += [Stack((size, (0.5, 0.5)), (1.0, 100.0)) for size in ((1.0, 0.25), (0.25, 1.0), (0.5, 0.1))]
    specs += [Stack(((0.5, 0.5), (0.5, 0.5)), (1.0, 100.0), (0.0, offset)) for offset in (0.1, -0.2)]
    specs.append(Stack(((0.5, 0.5),) * 3, (100.0, 10.0, 1.0)))
    return specs


def table(runs: dict, specs: list[Stack] | None = None, seconds: float = 5.0) -> str:
    """A markdown table of every variation (mm: end / largest over the run) for each named run:
    runs = {name: dict(config=..., params=..., add_floor=...)} (keys as measure's)."""
    specs = specs or variations()
    columns = {name: measure(specs, seconds, **run) for name, run in runs.items()}
    names = list(runs)
    lines = ["| stack (bottom to top) | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for k, spec in enumerate(specs):
        cells = []
        for name in names:
            r = columns[name][k]
            cell = ", ".join(f"{e * 1000:.1f}/{w * 1000:.1f}" for e, w in zip(r["between"], r["worst_between"],
                                                                               strict=True))
            cell += f"; {r['floor'] * 1000:.1f}/{r['worst_floor'] * 1000:.1f}"
            if r["frozen"] or r["x_drift"] > 0.005:
                cell += f" (drift {r['x_drift'] * 1000:.0f} mm, frozen {r['frozen']})"
            cells.append(cell)
        lines.append(f"| {spec.label} | " + " | ".join(cells) + " |")
    tested = [k for k, spec in enumerate(specs) if spec in set(variations())]
    if tested:
        worst = {name: max(columns[name][k]["sink"] for k in tested) for name in names}
        lines.append("| largest of the tested stacks (variations()) | "
                     + " | ".join(f"{worst[n] * 1000:.1f}" for n in names) + " |")
    return "\n".join(lines)


def main():
    runs = {"slab": dict(config=DEFAULT_CONFIG)}
    for seconds in (5.0, 10.0):
        print(f"\n{seconds:g} s: overlap between boxes (bottom pair first); with the floor. mm at the end / largest "
              "over the run")
        print(table(runs, variations() + extremes(), seconds=seconds))


if __name__ == "__main__":
    main()
