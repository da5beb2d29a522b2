"""The level model: a jax2d scene plus what the environment adds to it (roles and action bindings).

A `Level` is a pytree of fixed-capacity arrays, so levels of one size class stack and batch
under `vmap` like the `SimState` inside them. Behaviour that is not per-body state (episode
length, frame skip, reward scale, actuator scales) lives in `LevelParams`, and a loaded file
comes back as a `LevelFile` holding the level, its params and its size class.

Size classes follow the public Kinetix sizes; their polygon counts include the 4 static walls
of the standard 5 m x 5 m world, which are ordinary fixed polygons in slots 0-3.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from jax2d.state import COLLIDE_ALL, Capacity, SimParams, SimState, SolverConfig, empty_state

# Roles decide rewards: touching green to blue wins, green touching red loses.
ROLE_NONE, ROLE_GREEN, ROLE_BLUE, ROLE_RED = range(4)
ROLE_NAMES = ("none", "green", "blue", "red")

# Actions reach joints and thrusters through bindings: every joint listens to one of the
# motor bindings, every thruster to one of the thruster bindings (as in the public Kinetix).
NUM_MOTOR_BINDINGS = 4
NUM_THRUSTER_BINDINGS = 2


# Upper bound on capacities: the state keeps a contact slot for every pair of bodies (and scenes up to 40
# bodies check every pair in each step), so memory grows with the square.
MAX_BODIES = 256
MAX_JOINTS = MAX_THRUSTERS = 256


class LevelError(ValueError):
    """A level file or level that cannot be loaded, saved or fitted into a size class."""


@dataclasses.dataclass(frozen=True)
class SizeClass:
    """Entity capacities of a level. Hashable: one size class compiles one set of programs."""

    name: str
    polygons: int
    circles: int
    joints: int
    thrusters: int
    max_vertices: int = 8

    def __post_init__(self):
        for field in ("polygons", "circles", "joints", "thrusters", "max_vertices"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise LevelError(f"size {self.name}: {field} must be a non-negative integer, got {value!r}")
        if not 3 <= self.max_vertices <= 8:
            raise LevelError(f"size {self.name}: max_vertices must be in [3, 8], got {self.max_vertices}")
        if self.polygons + self.circles < 1:
            raise LevelError(f"size {self.name}: a level needs room for at least one body")
        if self.polygons + self.circles > MAX_BODIES or self.joints > MAX_JOINTS or self.thrusters > MAX_THRUSTERS:
            raise LevelError(f"size {self.name}: at most {MAX_BODIES} bodies, {MAX_JOINTS} joints and "
                             f"{MAX_THRUSTERS} thrusters are supported")

    @property
    def capacity(self) -> Capacity:
        return Capacity(self.polygons, self.circles, self.joints, self.thrusters, self.max_vertices)

    def counts(self) -> dict[str, int]:
        return dict(polygons=self.polygons, circles=self.circles, joints=self.joints, thrusters=self.thrusters)


SIZES: dict[str, SizeClass] = {
    "s": SizeClass("s", polygons=5, circles=2, joints=1, thrusters=1),
    "m": SizeClass("m", polygons=6, circles=3, joints=2, thrusters=2),
    "l": SizeClass("l", polygons=12, circles=4, joints=6, thrusters=2),
    # Levels bigger than l (issue 28): about five times l. xl scenes collide only close pairs, at any
    # batch size (jax2d.broad_phase, above AUTO_BODIES bodies; docs/engine.md).
    "xl": SizeClass("xl", polygons=64, circles=16, joints=24, thrusters=8),
}


def size_class(size: str | SizeClass) -> SizeClass:
    """`size` as a SizeClass: "s", "m", "l", "xl" or a SizeClass (returned as is)."""
    if isinstance(size, SizeClass):
        return size
    if isinstance(size, str) and size in SIZES:
        return SIZES[size]
    raise LevelError(f"unknown size {size!r}: use one of {', '.join(SIZES)} or a SizeClass")


def size_for_counts(polygons: int, circles: int, joints: int, thrusters: int, max_vertices: int = 8) -> SizeClass:
    """The smallest standard size holding these counts, else a custom size that holds exactly them."""
    for size in SIZES.values():
        if (polygons <= size.polygons and circles <= size.circles and joints <= size.joints
                and thrusters <= size.thrusters and max_vertices <= size.max_vertices):
            return size
    return SizeClass("custom", polygons, circles, joints, thrusters)


@dataclasses.dataclass(frozen=True)
class LevelParams:
    """Per-level settings that change behaviour but are not body state. Plain Python numbers (hashable).

    max_timesteps: episode length in agent steps.
    frame_skip: physics steps per agent step.
    dense_reward_scale: weight of the shaping reward (the public Kinetix default 0.1).
    dt, base_*: the physics time step and actuator scales (see jax2d.SimParams).
    """

    max_timesteps: int = 256
    frame_skip: int = 2
    dense_reward_scale: float = 0.1
    dt: float = 1.0 / 60.0
    base_motor_speed: float = 6.0
    base_motor_power: float = 900.0
    base_thruster_power: float = 10.0

    def sim_params(self, **overrides) -> SimParams:
        """jax2d SimParams with this level's time step and actuator scales (other fields default)."""
        values = dict(dt=self.dt, base_motor_speed=self.base_motor_speed, base_motor_power=self.base_motor_power,
                      base_thruster_power=self.base_thruster_power)
        return SimParams(**{**values, **overrides})


PHYSICS_PARAMS = ("dt", "base_motor_speed", "base_motor_power", "base_thruster_power")


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Level:
    """One level: the scene and, per entity, what the environment needs. Shapes: N bodies, J joints, T thrusters."""

    sim: SimState
    roles: jax.Array  # (N,) int32: ROLE_NONE / GREEN / BLUE / RED
    motor_bindings: jax.Array  # (J,) int32 in [0, NUM_MOTOR_BINDINGS)
    motor_auto: jax.Array  # (J,) bool: the joint is always driven at +1, whatever the action
    thruster_bindings: jax.Array  # (T,) int32 in [0, NUM_THRUSTER_BINDINGS)

    @property
    def capacity(self) -> Capacity:
        s = self.sim
        return Capacity(s.num_polygons, s.num_circles, s.num_joints, s.num_thrusters, s.max_vertices)


@dataclasses.dataclass(frozen=True)
class LevelFile:
    """What loading a file gives: the level, its params and its size class, plus where it came from."""

    level: Level
    params: LevelParams = LevelParams()
    size: SizeClass | None = None  # None: the size class matching the level's capacity
    name: str = ""
    format: str = "ours"  # the format it was read from: "ours" or "kinetix"
    warnings: tuple[str, ...] = ()  # things the loader changed or dropped, for the user to see

    def __post_init__(self):
        if self.size is None:
            object.__setattr__(self, "size", size_of(self.level))
        elif self.size.capacity != self.level.capacity:
            raise LevelError(f"size {self.size.name} has capacity {self.size.capacity}, but the level's arrays have "
                             f"{self.level.capacity}; use kinetix.levels.resize")


def make_level(sim: SimState, roles=None, motor_bindings=None, motor_auto=None, thruster_bindings=None) -> Level:
    """Wrap a scene as a Level; entity data not given defaults to role none, binding 0, not auto."""
    n, j, t = sim.num_bodies, sim.num_joints, sim.num_thrusters

    def array(value, shape, dtype):
        if value is None:
            return jnp.zeros(shape, dtype)
        out = jnp.asarray(value, dtype)
        if out.shape != shape:
            raise LevelError(f"expected shape {shape}, got {out.shape}")
        return out

    return Level(
        sim=sim,
        roles=array(roles, (n,), jnp.int32),
        motor_bindings=array(motor_bindings, (j,), jnp.int32),
        motor_auto=array(motor_auto, (j,), bool),
        thruster_bindings=array(thruster_bindings, (t,), jnp.int32),
    )


def size_of(level: Level) -> SizeClass:
    """The standard size class whose capacity the level has, else a custom one."""
    cap = level.capacity
    for size in SIZES.values():
        if size.capacity == cap:
            return size
    return SizeClass("custom", cap.polygons, cap.circles, cap.joints, cap.thrusters, cap.max_vertices)


# ---------------------------------------------------------------- the standard walls

# The public Kinetix world is the box x in [0, 5], y in [0.4, 5]: polygon 0 is the floor (top at
# y = 0.4), 1 the left wall (x <= 0), 2 the right wall (x >= 5), 3 the ceiling (bottom at y = 5).
# Values are those of the public level files as float32, recentred on each wall's centroid and
# counter-clockwise, so walls imported from those files equal these bitwise.
_TALL = [(-2.5, 5.2), (-2.5, -5.2), (2.5, -5.2), (2.5, 5.2)]
_SQUARE = [(-2.5, -2.5), (2.5, -2.5), (2.5, 2.5), (-2.5, 2.5)]
WALLS = (  # (name, centre, counter-clockwise vertices relative to the centre)
    ("floor", (2.5, -4.8), _TALL),
    ("left wall", (-2.5, 2.5), _SQUARE),
    ("right wall", (7.5, 2.5), _SQUARE),
    ("ceiling", (2.5, 10.2), _TALL),
)
NUM_WALLS = len(WALLS)


def add_walls(state: SimState) -> SimState:
    """Put the 4 standard static walls into polygon slots 0-3, which must exist and be free."""
    if state.num_polygons < NUM_WALLS:
        raise LevelError(f"the walls need {NUM_WALLS} polygon slots, this scene has {state.num_polygons}")
    if bool(np.any(np.asarray(state.bodies.active[:NUM_WALLS]))):
        raise LevelError("polygon slots 0-3 must be free for the walls")
    if state.max_vertices < 4:
        raise LevelError(f"the walls are quads, this scene allows {state.max_vertices} vertices")
    b = {name: np.array(getattr(state.bodies, name)) for name in ("position", "angle", "inv_mass", "inv_inertia",
                                                                  "collision_mode", "active", "vertices",
                                                                  "n_vertices", "friction", "restitution", "density")}
    for slot, (_, centre, vertices) in enumerate(WALLS):
        b["position"][slot] = centre
        b["angle"][slot] = 0.0
        b["vertices"][slot] = vertices + [vertices[-1]] * (state.max_vertices - 4)
        b["n_vertices"][slot] = 4
        b["inv_mass"][slot] = b["inv_inertia"][slot] = 0.0
        b["collision_mode"][slot] = COLLIDE_ALL
        b["friction"][slot], b["restitution"][slot], b["density"][slot] = 1.0, 0.0, 1.0
        b["active"][slot] = True
    bodies = dataclasses.replace(state.bodies, **{k: jnp.asarray(v) for k, v in b.items()})
    return dataclasses.replace(state, bodies=bodies)


# The solver for levels whose polygon slots 0-3 hold only static bodies (the standard walls, as in every
# public Kinetix level, every generated level and every level drawn in the editor): the contact sweeps may
# then group the walls' pairs into few colours (jax2d.pairs.wall_grouped; l steps ~20 % faster at batch 1).
WALLS_SOLVER = SolverConfig(num_static=NUM_WALLS)


def walls_static(level: Level) -> bool:
    """True when every body in polygon slots 0-3 is static or absent, so WALLS_SOLVER applies.

    Our format also allows a moving body there (a level without the standard walls); such a level
    needs the plain SolverConfig(), which checks every pair.
    """
    b = level.sim.bodies
    if level.sim.num_polygons < NUM_WALLS:
        return False
    active, inv_mass, inv_inertia = (np.asarray(x[:NUM_WALLS]) for x in (b.active, b.inv_mass, b.inv_inertia))
    return bool(np.all(~active | ((inv_mass == 0) & (inv_inertia == 0))))


def solver_for(levels) -> SolverConfig:
    """WALLS_SOLVER if every level given (one Level or several) keeps its walls static, else SolverConfig()."""
    levels = [levels] if isinstance(levels, Level) else list(levels)
    return WALLS_SOLVER if levels and all(walls_static(lv) for lv in levels) else SolverConfig()


def empty_level(size: str | SizeClass = "l", gravity=(0.0, -9.81)) -> Level:
    """A level of this size holding only the 4 standard walls."""
    size = size_class(size)
    return make_level(add_walls(empty_state(size.capacity, gravity)))
