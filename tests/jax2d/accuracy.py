"""The accuracy scenes of issue 28, shared by test_accuracy.py and its full report.

    python -m tests.jax2d.accuracy            # every figure, with the full crowded-scene counts (8 action keys)

Each scene returns plain numbers, so the tests assert on them and the report prints them.
Scenes (all with the defaults: dt = 1/60, SimParams(), SolverConfig()):
- cradle: three balls of radius 0.1 m, restitution 1, friction 0, no gravity, in a row on the x axis;
  the second and third touch, the first comes from 0.3 m away at 3 m/s. There is no string
  or floor: what is measured is the chain of impacts alone (a pendulum cradle adds gravity's
  slow swing, which changes nothing in the collisions). Kinetic energy after / before and the
  final velocities after 1 s; correct: 1 and (0, 0, 3).
- bounce: a ball of radius 0.1 m dropped from 1 m onto a static floor; the heights of its first
  two bounces against e^2 h and e^4 h.
- mass ratio: a 1 kg box (0.5 m) on the floor and a 100 kg box of the same size on it; after 5 s
  the overlap between the boxes and of the lower box with the floor.
- tunnel: a ball of diameter 0.1 m shot at a static wall 0.1 m thick, no gravity, from 5 start
  distances spread over one step's travel; how many end on the far side.
- crowded walls: the random crowded scenes of test_physics (motors and thrusters at full power);
  per step and scene, whether some dynamic body's centre is inside a static body.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from jax2d import scene
from jax2d.narrow_phase import joint_connected
from jax2d.state import COLLIDE_ALL, COLLIDE_NORMAL, modes_agree
from tests.jax2d import scenes
from tests.jax2d.scenes import rollout

PARAMS = jax2d.SimParams()
DT = 1.0 / 60.0
LITTLE = jax2d.Capacity(polygons=3, circles=3, joints=0, thrusters=0, max_vertices=4)
CROWDED = jax2d.Capacity(polygons=12, circles=4, joints=6, thrusters=2, max_vertices=8)  # the crowded scenes


def _empty(gravity=(0.0, -9.81)) -> jax2d.SimState:
    return jax2d.empty_state(LITTLE, gravity=gravity)


def cradle(speed: float = 3.0, seconds: float = 1.0) -> dict:
    """Three-ball Newton's cradle without strings (see the module docstring)."""
    radius = 0.1
    state = _empty(gravity=(0.0, 0.0))
    balls = []
    for x, v in ((-0.3 - 2 * radius, speed), (0.0, 0.0), (2 * radius, 0.0)):
        state, i = scene.add_circle(state, (x, 0.0), radius, restitution=1.0, friction=0.0, velocity=(v, 0.0))
        balls.append(i)
    mass, _ = scene.body_mass_properties(state, balls[0])
    final, _ = rollout(state, PARAMS, round(seconds / DT))
    v = np.asarray(final.bodies.velocity)[balls]
    w = np.asarray(final.bodies.angular_velocity)[balls]
    energy = 0.5 * mass * np.sum(v**2)
    return dict(energy_ratio=float(energy / (0.5 * mass * speed**2)), velocities=v[:, 0].tolist(),
                spin=float(np.abs(w).max()), frozen=int(final.frozen))


def bounce(e: float, drop: float = 1.0, seconds: float = 2.0) -> dict:
    """A ball dropped from `drop` m (its bottom) on a floor; both have restitution e."""
    radius = 0.1
    state, _ = scene.add_rectangle(_empty(), (0.0, -0.5), 40.0, 1.0, fixed=True, restitution=e)
    state, ball = scene.add_circle(state, (0.0, drop + radius), radius, restitution=e)
    _, rec = rollout(state, PARAMS, round(seconds / DT))
    bottom = rec["position"][:, ball, 1].astype(np.float64) - radius
    vy = rec["velocity"][:, ball, 1]
    apexes = []
    for k in range(1, len(vy) - 1):  # a rise that turns into a fall: the top of a bounce
        if vy[k - 1] > 0 >= vy[k] and len(apexes) < 2:
            apexes.append(float(bottom[k - 1:k + 1].max()))
    expected = [e**2 * drop, e**4 * drop]
    return dict(apexes=apexes, ratios=[a / x for a, x in zip(apexes, expected, strict=False)])


def mass_ratio(heavy: float = 100.0, light: float = 1.0, seconds: float = 5.0, params: jax2d.SimParams = PARAMS,
               config: jax2d.SolverConfig = scenes.DEFAULT_CONFIG) -> dict:
    """A heavy box on a light box on the floor; overlaps after `seconds` in m (positive = sinking)."""
    side = 0.5
    state, _ = scene.add_rectangle(_empty(), (0.0, -0.5), 40.0, 1.0, fixed=True)
    state, low = scene.add_rectangle(state, (0.0, side / 2), side, side, density=light / side**2)
    state, high = scene.add_rectangle(state, (0.0, 1.5 * side), side, side, density=heavy / side**2)
    final, rec = rollout(state, params, round(seconds / DT), config=config)
    y = rec["position"][:, [low, high], 1].astype(np.float64)
    between = side - (y[:, 1] - y[:, 0])
    floor = side / 2 - y[:, 0]
    return dict(between=float(between[-1]), floor=float(floor[-1]), worst_between=float(between.max()),
                worst_floor=float(floor.max()), x_drift=float(np.abs(rec["position"][-1, [low, high], 0]).max()),
                frozen=int(final.frozen))


def tunnel(speed: float, tries: int = 5, diameter: float = 0.1, thickness: float = 0.1) -> dict:
    """A ball shot along x at a static wall (its near face at x = 0); how many of `tries` end behind it."""
    radius = diameter / 2
    travel = speed * DT
    through = []
    for k in range(tries):
        state = _empty(gravity=(0.0, 0.0))
        state, _ = scene.add_rectangle(state, (thickness / 2, 0.0), thickness, 2.0, fixed=True)
        start = -radius - 0.2 - travel * (k + 0.5) / tries  # every phase of a step's travel
        state, ball = scene.add_circle(state, (start, 0.0), radius, velocity=(speed, 0.0))
        _, rec = rollout(state, PARAMS, scenes.CHUNK)  # 1 s
        through.append(bool(np.any(rec["position"][:, ball, 0] > thickness / 2)))
    return dict(tunnelled=int(sum(through)), tries=tries)


def _behind(rec: dict, body: int, plank: int, depth: float, half_length: float = 1.0, near: float = 4.0) -> bool:
    """Whether body's centre went from in front of the plank (x < 0 in its frame, as every scene here starts:
    the recording begins after the first step) to behind it (x > depth) while near it: within its length
    (|y| <= half_length) and |x| <= near in every step between (4 m: more than any relative travel in one step
    below the speed clamp). A free plank that the box sets spinning and flying off turns its back to a ball
    that is metres away or beyond its end; that is not a crossing."""
    rel = rec["position"][:, body] - rec["position"][:, plank]
    angle = rec["angle"][:, plank]
    x = np.cos(angle) * rel[:, 0] + np.sin(angle) * rel[:, 1]
    y = -np.sin(angle) * rel[:, 0] + np.cos(angle) * rel[:, 1]
    in_front = True
    for xi, yi in zip(x, y, strict=True):
        if abs(yi) > half_length or abs(xi) > near:
            in_front = False
        elif xi < 0.0:
            in_front = True
        elif xi > depth and in_front:
            return True
    return False


def speed_up_tunnel(speed: float, tries: int = 5, gap: float = 0.25, thickness: float = 0.03,
                    restitution: float = 0.0, ball_mode: int = COLLIDE_NORMAL, fixed: bool = True) -> dict:
    """A light 0.1 m ball at rest `gap` in front of a thin static wall (its near face at x = 0), hit from behind
    by a heavy 0.3 m box at `speed`, no gravity: how many of `tries` balls end behind the wall.

    The ball is at rest when its step starts, so the speculative margin (narrow_phase.step_reach) gives it no contact
    with the wall; the box's hit inside the step sends it off at up to 2x the box's speed. The tries start the
    box at every phase of a step's travel. ball_mode: the ball's collision mode (COLLIDE_ONLY_ALL: it ignores the
    wall, and passes). fixed=False: the wall is a free plank (1 kg/m^2, 76 times the ball's mass, a fifteenth of
    the box's), and "behind" is in its frame."""
    radius = 0.05
    travel = speed * DT
    through = []
    for k in range(tries):
        state = _empty(gravity=(0.0, 0.0))
        state, wall = scene.add_rectangle(state, (thickness / 2, 0.0), thickness, 2.0, fixed=fixed)
        state, ball = scene.add_circle(state, (-gap - radius, 0.0), radius, density=0.1, restitution=restitution,
                                     collision_mode=ball_mode)
        start = -gap - 2 * radius - 0.15 - 0.05 - travel * (k + 0.5) / tries
        state, _ = scene.add_rectangle(state, (start, 0.0), 0.3, 0.3, density=10.0, velocity=(speed, 0.0),
                                     collision_mode=COLLIDE_ALL)  # it hits the ball in every mode
        _, rec = rollout(state, PARAMS, scenes.CHUNK)  # 1 s
        through.append(_behind(rec, ball, wall, thickness / 2 + radius))
    return dict(tunnelled=int(sum(through)), tries=tries)


def thrust_through_a_dynamic_plank(accel: float = 3000.0, tries: int = 12, thickness: float = 0.03,
                                   plank_density: float = 1.0, fixed: bool = False) -> dict:
    """A light 0.1 m ball (0.1 kg/m^2) pushed along x by a thruster at `accel` m/s^2 from rest, no gravity, toward
    a free (dynamic) plank 3 cm x 2 m, 76 times its mass, from `tries` start distances between 0.05 and 3 m:
    how many balls end up through the plank (their centre past its far face, in the plank's frame, at some step).

    The speculative margin covers the travel of a body's velocity at the step's start; the thrust adds
    accel dt^2 / 2 within the step (0.42 m at 3,000 m/s^2), and the ball's speed reaches the clamp (100 m/s)
    after two steps, so the ball meets the plank at every speed up to the clamp. fixed: a static plank."""
    radius = 0.05
    capacity = jax2d.Capacity(polygons=1, circles=1, joints=0, thrusters=1, max_vertices=4)
    through = []
    for gap in np.linspace(0.05, 3.0, tries):
        state = jax2d.empty_state(capacity, gravity=(0.0, 0.0))
        state, plank = scene.add_rectangle(state, (thickness / 2, 0.0), thickness, 2.0, density=plank_density,
                                         fixed=fixed)
        state, ball = scene.add_circle(state, (-gap - radius, 0.0), radius, density=0.1)
        mass, _ = scene.body_mass_properties(state, ball)
        power = accel * mass / PARAMS.base_thruster_power
        state, _ = scene.add_thruster(state, ball, (-gap - radius, 0.0), angle=0.0, power=power)
        _, rec = rollout(state, PARAMS, scenes.CHUNK, thruster_actions=np.ones(1, np.float32))  # 1 s
        through.append(_behind(rec, ball, plank, thickness / 2))
    return dict(tunnelled=int(sum(through)), tries=tries)


# ---------------------------------------------------------------- walls against motors


def _inside_static(state: jax2d.SimState) -> jax.Array:
    """(N,) whether each active dynamic body's centre lies strictly inside some active static polygon that it
    collides with (not one it is linked to by a chain of joints, nor one its collision mode ignores)."""
    b = state.bodies
    P = state.num_polygons
    static = b.active[:P] & (b.inv_mass[:P] == 0)
    cos, sin = jnp.cos(b.angle[:P]), jnp.sin(b.angle[:P])
    d = b.position[None, :, :] - b.position[:P, None, :]  # (P, N, 2) centre relative to polygon p
    lx = cos[:, None] * d[..., 0] + sin[:, None] * d[..., 1]
    ly = -sin[:, None] * d[..., 0] + cos[:, None] * d[..., 1]
    v = b.vertices  # (P, V, 2)
    V = v.shape[1]
    nxt = jnp.roll(v, -1, axis=1)
    nxt = jnp.where((jnp.arange(V)[None, :] == b.n_vertices[:, None] - 1)[..., None], v[:, :1], nxt)
    edge = nxt - v
    # Inside a convex counter-clockwise polygon: left of every edge.
    cross = edge[:, None, :, 0] * (ly[..., None] - v[:, None, :, 1]) - edge[:, None, :, 1] * (lx[..., None]
                                                                                          - v[:, None, :, 0])
    used = jnp.arange(V)[None, None, :] < b.n_vertices[:, None, None]
    inside = jnp.all((cross > 0) | ~used, axis=-1)  # (P, N)
    dynamic = b.active & (b.inv_mass > 0)
    mode = b.collision_mode
    collide = modes_agree(mode[:P, None], mode[None, :])
    linked = joint_connected(state.joints, b.active.shape[0])[:P]
    return jnp.any(inside & static[:, None] & collide & ~linked, axis=0) & dynamic


@functools.partial(jax2d.jit, static_argnames=("steps", "config"))
def _crowded_run(states: jax2d.SimState, key: jax.Array, steps: int,
                 config: jax2d.SolverConfig = scenes.DEFAULT_CONFIG):
    """Random actions at full power; per step and scene (steps, B): whether a centre is inside a static body, the
    bodies the NaN guard froze, and the largest linear speed."""
    batch, joints, thrusters = states.bodies.active.shape[0], states.num_joints, states.num_thrusters
    step = jax.vmap(lambda s, m, t: scenes.STEP(s, PARAMS, m, t, config=config))

    def body(s, key):
        km, kt = jax.random.split(key)
        motors = jnp.sign(jax.random.uniform(km, (batch, joints), minval=-1.0, maxval=1.0))  # full power
        thrusts = (jax.random.uniform(kt, (batch, thrusters)) > 0.5).astype(jnp.float32)
        s = step(s, motors, thrusts)
        speed = jnp.max(jnp.linalg.norm(s.bodies.velocity, axis=-1), axis=-1)
        return s, (jnp.any(jax.vmap(_inside_static)(s), axis=-1), s.frozen, speed)

    _, (inside, frozen, speed) = jax.lax.scan(body, states, jax.random.split(key, steps))
    return inside, frozen, speed


def crowded_walls(scene_count: int = 64, steps: int = 2000, seed: int = 0, first_scene: int = 0,
                  num_static: int = 0) -> dict:
    """Steps (of scene_count x steps) in which some dynamic centre is inside a static body, and the scenes.
    seed: the random actions' key; the scenes are random_scene(first_scene ...); num_static: the solver's
    SolverConfig.num_static (the scenes' 4 walls come first, so 4 is the Kinetix environment's solver)."""
    built = [scenes.random_scene(s, CROWDED)[0] for s in range(first_scene, first_scene + scene_count)]
    config = jax2d.SolverConfig(num_static=num_static)
    inside, frozen, _ = _crowded_run(scenes.stack(built), jax.random.key(seed), steps, config)
    inside = np.asarray(inside)
    return dict(steps_inside=int(inside.sum()),
                scenes_inside=(first_scene + np.nonzero(inside.any(axis=0))[0]).tolist(),
                total=inside.size, frozen=int(np.asarray(frozen).sum()))


def crowded_runaways(scene_ids: tuple[int, ...], steps: int = 600, seed: int = 1) -> dict:
    """The crowded scenes `scene_ids`, stepped as one batch with random full-power actions (key `seed`): which of
    them had a body the NaN guard froze, and which had a body at RUNAWAY_SPEED or faster (a body at half the clamp
    is a solver running away: with the torn-joint cap the fastest body of scenes 329, 385, 441 and 509 reached
    41 m/s in 600 steps, without it they ran at the 100 m/s clamp)."""
    built = [scenes.random_scene(s, CROWDED)[0] for s in scene_ids]
    _, frozen, speed = _crowded_run(scenes.stack(built), jax.random.key(seed), steps)
    frozen, speed = np.asarray(frozen), np.asarray(speed)
    return dict(frozen=[s for s, f in zip(scene_ids, frozen.any(axis=0), strict=True) if f],
                runaway=[s for s, f in zip(scene_ids, (speed >= RUNAWAY_SPEED).any(axis=0), strict=True) if f],
                top_speed=float(speed.max()))


RUNAWAY_SPEED = 0.5 * PARAMS.max_linear_speed


def main() -> None:
    print("cradle", cradle())
    for e in (0.5, 0.8, 1.0):
        print(f"bounce e={e}", bounce(e))
    print("mass ratio 100:1", mass_ratio())
    for speed in (10.0, 30.0, 60.0, 100.0):
        print(f"tunnel {speed} m/s", tunnel(speed))
    for speed in (30.0, 60.0):
        for e in (0.0, 1.0):
            print(f"tunnel after a speed-up, box at {speed} m/s, ball e={e}", speed_up_tunnel(speed, restitution=e))
    for speed in (10.0, 30.0, 60.0):
        print(f"through a free plank after a speed-up, box at {speed} m/s", speed_up_tunnel(speed, fixed=False))
    for accel in (1000.0, 3000.0, 10000.0):
        print(f"a thruster at {accel} m/s^2 through a dynamic plank", thrust_through_a_dynamic_plank(accel))
    for seed in range(8):
        print(f"crowded walls 64 x 2000, actions key {seed}", crowded_walls(seed=seed))
    print("crowded runaways, scenes 329, 385, 441, 509, key 1", crowded_runaways((329, 385, 441, 509)))
    for first in (64, 128):
        print(f"crowded walls, scenes {first}-{first + 63} x 2000, key 0", crowded_walls(first_scene=first))


if __name__ == "__main__":
    main()
