"""Level mutators: small random edits that keep a level valid, for curricula and the editor's "shake it up".

    level = mutate(key, level, n=3)                        # three random edits
    level = mutate_move(key, level, "m")                   # one particular edit

Every mutator is pure JAX (jit / vmap-able), takes `(key, level, size)` and returns a level of the same
shapes. An edit is made only if the result stays valid (`kinetix.generate.is_valid`: a green and a blue
body that can touch and are not both fixed, a motor or thruster on a dynamic body, joints and thrusters
on active bodies) and, for edits that place shapes, if the placed shapes lie inside the walls with
(almost) no overlap; otherwise the level comes back unchanged. Jointed bodies move and rotate as one
assembly, so joints stay closed. Every output has fresh warm-start data (no contact or joint impulses).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from jax2d.state import Contacts
from kinetix.generate import (
    valid_masks,
)
from kinetix.geometry import (
    HULL,
    WORLD_BOTTOM,
    WORLD_LEFT,
    WORLD_RIGHT,
    WORLD_TOP,
    body_hulls,
    groups_from_joints,
    joint_groups,
    set_fixed,
    wall_mask,
    world_hulls,
)
from kinetix.level import NUM_WALLS, ROLE_GREEN, ROLE_NONE, ROLE_RED, Level, SizeClass, size_class
from kinetix.placement import (
    DEFAULT_PARAMS,
    PROPOSAL_DRAWS,
    THRUSTER_DRAWS,
    GeneratorParams,
    Stream,
    add_body,
    add_body_draws,
    add_thruster,
    placement_cost,
)

_BIG = 1e9
MAX_MOVE = 0.5  # m, per axis
MAX_TURN = jnp.pi / 2
MIN_SCALE, MAX_SCALE = 0.6, 1.5


def _check_size(level: Level, size) -> None:
    if size is not None and size_class(size).capacity != level.capacity:
        raise ValueError(f"size {size_class(size).name} does not match the level's capacity {level.capacity}")


def _fresh(level: Level) -> Level:
    """The level without warm-start data: geometry changed, so old impulses would be wrong."""
    c = level.sim.contacts
    contacts = Contacts(jnp.zeros_like(c.normal_impulse), jnp.zeros_like(c.tangent_impulse),
                        jnp.full_like(c.key, -1), jnp.zeros_like(c.active), jnp.zeros_like(c.separation))
    joints = dataclasses.replace(level.sim.joints, impulse=jnp.zeros_like(level.sim.joints.impulse))
    return dataclasses.replace(level, sim=dataclasses.replace(level.sim, contacts=contacts, joints=joints))


def _select(condition, new: Level, old: Level) -> Level:
    return jax.tree.map(lambda a, b: jnp.where(condition, a, b), new, old)


def _editable(level: Level) -> jax.Array:
    """(N,) bodies a mutator may pick: active, not walls, not jointed to a wall."""
    b = level.sim.bodies
    groups = joint_groups(level)
    wall_group = jnp.any((groups[:, None] == groups[None, :]) & wall_mask(level)[None, :], axis=1)
    return b.active & ~wall_mask(level) & ~wall_group


def _validity(level: Level, roles=None, active=None, fixed=None, joint_active=None, thruster_active=None,
              groups=None):
    """is_valid of the level with some masks replaced (groups recomputed from the joints unless given)."""
    b, j, t = level.sim.bodies, level.sim.joints, level.sim.thrusters
    roles = level.roles if roles is None else roles
    active = b.active if active is None else active
    fixed = (b.inv_mass == 0) if fixed is None else fixed
    joint_active = j.active if joint_active is None else joint_active
    thruster_active = t.active if thruster_active is None else thruster_active
    if groups is None:
        groups = groups_from_joints(j.a, j.b, joint_active, level.sim.num_bodies)
    return valid_masks(roles, active, fixed, groups, joint_active, j.a, j.b, joint_active & ~j.fixed & j.motor_on,
                       thruster_active, t.body)


def _group_fits(level: Level, moved, position, angle, hulls, counts, params: GeneratorParams):
    """(cost, fits) of the `moved` bodies at new poses against every other collidable body."""
    worlds = world_hulls(position, angle, hulls)
    others = level.sim.bodies.active & ~wall_mask(level) & ~moved
    cost, fits = jax.vmap(placement_cost, in_axes=(0, 0, None, None, None, None))(
        worlds, counts, worlds, counts, others, params)
    return jnp.sum(jnp.where(moved, cost, 0.0)), jnp.all(fits | ~moved)


def _best_pose(level: Level, u: Stream, params: GeneratorParams, propose):
    """Pick a body, move its joint group by the best of `params.proposals` proposals, keep it if it fits.

    propose(stream, body, group_mask) -> (positions (N, 2), angles (N,), hulls) for the whole level.
    """
    body = u.choice(_editable(level))
    groups = joint_groups(level)
    moved = (groups == groups[body]) & level.sim.bodies.active
    hulls, counts = body_hulls(level)

    def one(numbers):
        position, angle, new_hulls = propose(Stream(numbers), body, moved, hulls)
        cost, fits = _group_fits(level, moved, position, angle, new_hulls, counts, params)
        return cost, fits, position, angle

    cost, fits, position, angle = jax.vmap(one)(u.sub(params.proposals, PROPOSAL_DRAWS))
    best = jnp.argmin(cost + jnp.where(fits, 0.0, _BIG))
    ok = jnp.any(_editable(level)) & fits[best]
    return body, moved, position[best], angle[best], ok


def _stream(key, params: GeneratorParams) -> Stream:
    return Stream.of(key, 16 + max(add_body_draws(params), params.proposals * PROPOSAL_DRAWS + 8))


# ---------------------------------------------------------------- the mutators


def mutate_add_shape(key, level: Level, size: SizeClass | str | None = None,
                     params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Add a random free or jointed shape (sometimes fixed, sometimes red) where there is room."""
    _check_size(level, size)
    u = _stream(key, params)
    b = level.sim.bodies
    P = level.sim.num_polygons
    polygons_left = jnp.sum(~b.active[NUM_WALLS:P])
    circles_left = jnp.sum(~b.active[P:])
    is_circle = u.take() * (polygons_left + circles_left) >= polygons_left
    connect, fixed, red = u.chance(0.5), u.chance(params.fixed_chance), u.chance(params.red_chance)
    result = add_body(u, level, params, is_circle=is_circle, connect=connect, fixed=fixed,
                      role=jnp.where(red, ROLE_RED, ROLE_NONE))
    return _select(result.added, _fresh(result.level), level)


def mutate_remove_shape(key, level: Level, size: SizeClass | str | None = None,
                        params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Remove a random shape with its joints and thrusters, if the level stays valid without it."""
    _check_size(level, size)
    u = _stream(key, params)
    sim = level.sim
    N = sim.num_bodies

    def without(i):
        gone = jnp.arange(N) == i
        joints = sim.joints.active & ~gone[sim.joints.a] & ~gone[sim.joints.b]
        thrusters = sim.thrusters.active & ~gone[sim.thrusters.body]
        return gone, joints, thrusters

    def valid(i):
        gone, joints, thrusters = without(i)
        return _validity(level, roles=jnp.where(gone, ROLE_NONE, level.roles), active=sim.bodies.active & ~gone,
                         joint_active=joints, thruster_active=thrusters)

    allowed = _editable(level) & jax.vmap(valid)(jnp.arange(N))
    i = u.choice(allowed)
    gone, joints, thrusters = without(i)
    b = sim.bodies
    bodies = dataclasses.replace(b, active=b.active & ~gone, inv_mass=jnp.where(gone, 0.0, b.inv_mass),
                                 inv_inertia=jnp.where(gone, 0.0, b.inv_inertia),
                                 velocity=jnp.where(gone[:, None], 0.0, b.velocity),
                                 angular_velocity=jnp.where(gone, 0.0, b.angular_velocity))
    new = dataclasses.replace(
        level, roles=jnp.where(gone, ROLE_NONE, level.roles),
        sim=dataclasses.replace(sim, bodies=bodies, joints=dataclasses.replace(sim.joints, active=joints),
                                thrusters=dataclasses.replace(sim.thrusters, active=thrusters)))
    return _select(jnp.any(allowed), _fresh(new), level)


def _with_poses(level: Level, moved, position, angle) -> Level:
    b = level.sim.bodies
    bodies = dataclasses.replace(b, position=jnp.where(moved[:, None], position, b.position),
                                 angle=jnp.where(moved, angle, b.angle))
    return dataclasses.replace(level, sim=dataclasses.replace(level.sim, bodies=bodies))


def mutate_move(key, level: Level, size: SizeClass | str | None = None,
                params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Shift a random shape (with everything jointed to it) by up to MAX_MOVE per axis, inside the walls."""
    _check_size(level, size)
    u = _stream(key, params)
    b = level.sim.bodies

    def propose(v: Stream, body, moved, hulls):
        worlds = world_hulls(b.position, b.angle, hulls)
        low = jnp.min(jnp.where(moved[:, None, None], worlds, _BIG), axis=(0, 1))
        high = jnp.max(jnp.where(moved[:, None, None], worlds, -_BIG), axis=(0, 1))
        # Keep the assembly's bounding box inside the walls (when it fits at all).
        lo = jnp.maximum(jnp.array([WORLD_LEFT, WORLD_BOTTOM]) - low, -MAX_MOVE)
        hi = jnp.minimum(jnp.array([WORLD_RIGHT, WORLD_TOP]) - high, MAX_MOVE)
        shift = lo + v.take((2,)) * jnp.maximum(hi - lo, 0.0)
        return b.position + shift, b.angle, hulls

    _, moved, position, angle, ok = _best_pose(level, u, params, propose)
    return _select(ok, _fresh(_with_poses(level, moved, position, angle)), level)


def mutate_rotate(key, level: Level, size: SizeClass | str | None = None,
                  params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Turn a random shape (with everything jointed to it) about its centre by up to MAX_TURN either way."""
    _check_size(level, size)
    u = _stream(key, params)
    b = level.sim.bodies

    def propose(v: Stream, body, moved, hulls):
        turn = v.uniform(-MAX_TURN, MAX_TURN)
        c, s = jnp.cos(turn), jnp.sin(turn)
        d = b.position - b.position[body]
        rotated = b.position[body] + jnp.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]], axis=-1)
        return rotated, b.angle + turn, hulls

    _, moved, position, angle, ok = _best_pose(level, u, params, propose)
    return _select(ok, _fresh(_with_poses(level, moved, position, angle)), level)


def mutate_resize(key, level: Level, size: SizeClass | str | None = None,
                  params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Scale a random shape about its centre of mass and recompute its mass.

    Joint anchors stay where they are (so joints stay closed); thrusters on it move with its surface and
    their power scales with its mass.
    """
    _check_size(level, size)
    u = _stream(key, params)
    sim = level.sim
    b = sim.bodies
    P, N = sim.num_polygons, sim.num_bodies
    index = jnp.arange(N)

    def scale_limits(body, hulls):
        reach = jnp.max(jnp.linalg.norm(hulls[body], axis=-1))
        is_circle = body >= P
        smallest = jnp.where(is_circle, 0.5 * params.min_circle_radius / jnp.cos(jnp.pi / HULL),
                             0.5 * params.min_polygon_size)
        largest = jnp.where(is_circle, params.max_circle_radius * params.large_shape_factor / jnp.cos(jnp.pi / HULL),
                            params.max_polygon_size * params.large_shape_factor * params.max_aspect ** 0.5)
        return jnp.maximum(MIN_SCALE, smallest / reach), jnp.minimum(MAX_SCALE, largest / reach)

    def propose(v: Stream, body, moved, hulls):
        low, high = scale_limits(body, hulls)
        factor = jnp.where(low < high, v.uniform(0.0, 1.0) * (high - low) + low, 1.0)
        return b.position, b.angle, jnp.where((index == body)[:, None, None], hulls * factor, hulls)

    # Only the chosen body changes shape, so only it is tested against the others.
    body = u.choice(_editable(level))
    groups = joint_groups(level)
    hulls, counts = body_hulls(level)
    alone = index == body
    others = b.active & ~wall_mask(level) & (groups != groups[body])

    def one(numbers):
        _, _, new_hulls = propose(Stream(numbers), body, alone, hulls)
        worlds = world_hulls(b.position, b.angle, new_hulls)
        cost, fits = placement_cost(worlds[body], counts[body], worlds, counts, others, params)
        factor = jnp.max(jnp.linalg.norm(new_hulls[body], axis=-1)) / jnp.max(jnp.linalg.norm(hulls[body], axis=-1))
        return cost, fits, factor

    cost, fits, factor = jax.vmap(one)(u.sub(params.proposals, PROPOSAL_DRAWS))
    best = jnp.argmin(cost + jnp.where(fits, 0.0, _BIG))
    ok = jnp.any(_editable(level)) & fits[best]
    f = factor[best]

    vertices = jnp.where((jnp.arange(P) == body)[:, None, None], b.vertices * f, b.vertices)
    radius = jnp.where(jnp.arange(sim.num_circles) == body - P, b.radius * f, b.radius)
    t = sim.thrusters
    on_body = t.active & (t.body == body)
    thrusters = dataclasses.replace(
        t, anchor=jnp.where(on_body[:, None], t.anchor * f, t.anchor),
        power=jnp.where(on_body, jnp.minimum(t.power * f * f, params.max_thruster_power), t.power))
    new = dataclasses.replace(level, sim=dataclasses.replace(
        sim, bodies=dataclasses.replace(b, vertices=vertices, radius=radius), thrusters=thrusters))
    new = set_fixed(new, b.inv_mass == 0)  # recompute mass and inertia from the new shape
    return _select(ok, _fresh(new), level)


def mutate_swap_roles(key, level: Level, size: SizeClass | str | None = None,
                      params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Swap the roles of two shapes with different roles (e.g. which one is green), keeping the level valid."""
    _check_size(level, size)
    u = _stream(key, params)
    N = level.sim.num_bodies
    roles = level.roles
    editable = _editable(level)
    index = jnp.arange(N)
    groups = joint_groups(level)

    def swapped(i, j):
        return jnp.where(index == i, roles[j], jnp.where(index == j, roles[i], roles))

    def valid(i, j):
        differ = editable[i] & editable[j] & (i < j) & (roles[i] != roles[j])
        return differ & _validity(level, roles=swapped(i, j), groups=groups)

    pairs = jax.vmap(lambda i: jax.vmap(lambda j: valid(i, j))(index))(index).reshape(-1)
    pick = u.choice(pairs)
    new = dataclasses.replace(level, roles=swapped(pick // N, pick % N))
    return _select(jnp.any(pairs), _fresh(new), level)


def mutate_add_thruster(key, level: Level, size: SizeClass | str | None = None,
                        params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Attach a thruster (random binding, power a few times the weight it pushes) to a dynamic shape."""
    _check_size(level, size)
    u = Stream.of(key, THRUSTER_DRAWS)
    green = jnp.argmax(level.roles == ROLE_GREEN)
    new, added = add_thruster(u, level, params, prefer=green)
    return _select(added, _fresh(new), level)


def mutate_toggle_fixed(key, level: Level, size: SizeClass | str | None = None,
                        params: GeneratorParams = DEFAULT_PARAMS) -> Level:
    """Make a random shape fixed or dynamic (mass and inertia from its density), keeping the level valid."""
    _check_size(level, size)
    u = _stream(key, params)
    N = level.sim.num_bodies
    fixed = level.sim.bodies.inv_mass == 0
    index = jnp.arange(N)
    groups = joint_groups(level)
    toggled = lambda i: fixed ^ (index == i)
    allowed = _editable(level) & jax.vmap(lambda i: _validity(level, fixed=toggled(i), groups=groups))(index)
    i = u.choice(allowed)
    return _select(jnp.any(allowed), _fresh(set_fixed(level, toggled(i))), level)


MUTATORS = (
    mutate_add_shape,
    mutate_remove_shape,
    mutate_move,
    mutate_resize,
    mutate_rotate,
    mutate_swap_roles,
    mutate_add_thruster,
    mutate_toggle_fixed,
)
# Relative chance of each mutator in `mutate`: mostly reshaping, fewer structural changes.
MUTATOR_WEIGHTS = (1.0, 0.5, 1.0, 1.0, 1.0, 1.0, 0.5, 0.3)


def mutate(key, level: Level, n: int = 1, params: GeneratorParams = DEFAULT_PARAMS,
           weights: tuple[float, ...] = MUTATOR_WEIGHTS) -> Level:
    """Apply `n` mutators drawn by `weights` (an edit with nothing valid to do leaves the level as it is)."""
    if len(weights) != len(MUTATORS):
        raise ValueError(f"expected {len(MUTATORS)} weights, got {len(weights)}")
    branches = [lambda k, lv, m=m: m(k, lv, None, params) for m in MUTATORS]
    cumulative = jnp.cumsum(jnp.asarray(weights, jnp.float32))

    def one(level, k):
        k_pick, k_edit = jax.random.split(k)
        pick = jnp.sum(cumulative <= jax.random.uniform(k_pick) * cumulative[-1])
        return jax.lax.switch(jnp.minimum(pick, len(MUTATORS) - 1), branches, k_edit, level), None

    level, _ = jax.lax.scan(one, level, jax.random.split(key, n))
    return level
