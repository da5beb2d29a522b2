"""One physics step, as a pipeline of stages (Box2D v3's soft step).

    narrow phase            contact manifolds for every pair slot, once per step
    prepare                 contact and joint constraints, warm-start impulses matched by feature key
    substeps x n:
        integrate velocities    gravity and thrusters
        warm start              last impulses, applied all at once
        solve                   joints then contacts, with soft position bias
        integrate positions
        relax                   joints then contacts, without bias (removes bias energy)
    restitution             impacts propagated through touching chains, then bounces (restitution.py)
    joint projection        all joints' point and weld rows solved at once, on velocities and positions
    static walls            fast bodies swept back to where they enter a static body; bodies pushed out of
                            static ones beyond 2 slops, alternating with the projection (static_walls.py)
    store                   impulses for the next step; clamp and NaN guard (SimState.frozen counts the
                            bodies it froze)

Inside the step every body quantity is its own array over M padded bodies
(math2d.Vel / Pose); M is the body count rounded up to even, the extra body a
static dummy that padding contact slots point at. Every stage but the store runs
on a batch of scenes with the batch as the last axis, (M, B) per body (see
step_batch).
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.custom_batching import custom_vmap

from jax2d import broad_phase, compiling, contact_solver, joint_solver, static_walls
from jax2d.collide import Manifold, collide_circles, collide_polygon_circle, collide_polygons
from jax2d.compact import Compact, unpack, update
from jax2d.math2d import Pose, Softness, Vel, one_hot_rows, pick_rows, rotate, soft, take_rows
from jax2d.pairs import CIRCLE_CIRCLE, CIRCLE_POLY, PADDING, POLY_CIRCLE, POLY_POLY, ContactLayout, contact_layout
from jax2d.restitution import restitution
from jax2d.state import Bodies, Contacts, Joints, SimParams, SimState, SolverConfig, Thrusters, modes_agree

DEFAULT_CONFIG = SolverConfig()


def step(state: SimState, params: SimParams, motor_actions: jax.Array, thruster_actions: jax.Array,
         config: SolverConfig = DEFAULT_CONFIG) -> SimState:
    """Advance one scene by params.dt. Pure; jit with `config` static, vmap over scenes freely.

    motor_actions: (J,) in [-1, 1], scaled by each joint's motor speed.
    thruster_actions: (T,) in [0, 1], scaled by each thruster's power.

    Under `jax.vmap` this runs as `step_batch` (a custom batching rule), which lays the
    solver's arrays out batch-last; a single call is `step_batch` on a batch of one, so
    batched and single runs execute the same code.
    """
    return _vmappable(config)(state, params, motor_actions, thruster_actions)


def step_compact(state: Compact, params: Compact, motor_actions: jax.Array, thruster_actions: jax.Array,
                 config: SolverConfig = DEFAULT_CONFIG) -> Compact:
    """`step` on a packed state and packed params (jax2d.compact), returning the packed new state.

    For a Python loop at batch 1 (an interactive session): a jitted call then passes 4 leaves
    and returns 1 instead of 56 and 39, which at s was as costly as the step itself.
    """
    scene = unpack(state)
    return update(state, scene, step(scene, unpack(params), motor_actions, thruster_actions, config))


def step_batch(states: SimState, params: SimParams, motor_actions: jax.Array, thruster_actions: jax.Array,
               config: SolverConfig = DEFAULT_CONFIG) -> SimState:
    """Advance B scenes stacked on a leading axis. params: shared (scalar leaves) or per scene ((B,) leaves).

    The store runs per scene (vmap). The narrow phase, preparation and the substep loop run on
    batch-last arrays (per body (M, B), per slot (C, F, K, B)): under a plain vmap the batch
    would be the major axis and each colour's K slots the minor one, and XLA's CPU loops then
    move a handful of floats per row; batch-last they stream over B (measured 2x on the sweeps).
    """
    B = states.bodies.active.shape[0]
    params = jax.tree.map(lambda x: jnp.broadcast_to(jnp.asarray(x, jnp.float32), (B,)), params)
    chunks = -(-B // config.chunk)
    if chunks == 1 or B % chunks:
        return _step_chunk(states, params, motor_actions, thruster_actions, config)
    # On the CPU, step the batch in `chunks` equal parts one after the other, so a part's constraint
    # rows stay in the CPU's cache. Part c holds scenes c, c + chunks, c + 2 chunks, ...: a split of the
    # batch axis over devices (kinetix.devices) then splits every part the same way. On a GPU or TPU the
    # parts would run one after the other on a device made for running them side by side (a 256-scene
    # part fills a fraction of it: env l stayed at 31k steps/s from batch 256 to 16,384 on an H100), so
    # there the whole batch is one pass.
    in_parts = functools.partial(_step_in_parts, chunks=chunks, config=config)
    whole = functools.partial(_step_chunk, config=config)
    only = compiling.only_platform()
    if only is not None:  # one backend in this process (a CPU-only machine): decided here, traced once
        return (in_parts if only == "cpu" else whole)(states, params, motor_actions, thruster_actions)
    # Several (a GPU machine also has the CPU): the platform the program is lowered for decides
    # (lax.platform_dependent traces both ways, about twice the step's trace time; XLA sees one).
    return jax.lax.platform_dependent(states, params, motor_actions, thruster_actions, cpu=in_parts, default=whole)


def _step_in_parts(states: SimState, params: SimParams, motor_actions, thruster_actions, *, chunks: int,
                   config: SolverConfig):
    """step_batch in `chunks` interleaved equal parts, one after the other (lax.map); params per scene."""
    B = states.bodies.active.shape[0]
    size = B // chunks

    def split(x):
        return jnp.moveaxis(x.reshape((size, chunks) + x.shape[1:]), 1, 0)

    def join(x):
        return jnp.moveaxis(x, 0, 1).reshape((B,) + x.shape[2:])

    parts = jax.tree.map(split, (states, params, motor_actions, thruster_actions))
    return jax.tree.map(join, jax.lax.map(lambda part: _step_chunk(*part, config), parts))


def _step_chunk(states: SimState, params: SimParams, motor_actions, thruster_actions, config: SolverConfig):
    """step_batch on one part of the batch (params already per scene)."""
    layout = contact_layout(states.num_polygons, states.num_circles, config.num_static)
    if broad_phase.uses_broad_phase(config.broad_phase, layout.num_bodies):
        return _step_chunk_broad(layout, states, params, motor_actions, thruster_actions, config)
    M = layout.num_padded
    # The joint closure runs per scene; from there on every array is batch-last.
    jointed = jax.vmap(lambda j: joint_connected(j, M)[layout.slot_a, layout.slot_b])(states.joints)
    last = functools.partial(jax.tree.map, lambda x: jnp.moveaxis(x, 0, -1))
    scene = last(states)
    reach = step_reach(scene, params.dt)
    manifold = narrow_phase(layout, scene.bodies, params.speculative_distance, reach)
    loop, valid, _ = _prepare(layout, scene, params, last(motor_actions), last(thruster_actions), manifold,
                              last(jointed), reach, config)
    pose, vel, cimp, jimp = _solve(layout, loop, config)
    first = functools.partial(jax.tree.map, lambda x: jnp.moveaxis(x, -1, 0))
    pose, vel, cimp, jimp, manifold, valid, dyn = first((pose, vel, cimp, jimp, manifold, valid, loop.dyn))
    cimp = jax.vmap(functools.partial(contact_solver.unpack_impulses, layout))(cimp)
    return jax.vmap(_store)(states, params, pose, vel, cimp, jimp, manifold, valid, dyn)


def _solve(layout, loop: LoopData, config: SolverConfig):
    """Substeps, restitution and the joint projection on the prepared loop data (batch-last)."""
    colours = contact_solver.schedule(loop.const)
    joints = joint_solver.schedule(loop.jc)
    pose, vel, cimp, jimp = _substeps(layout, loop, colours, joints, config)
    gap = functools.partial(contact_solver.current_separation, layout, loop.cc, pose, loop.pose0,
                            jnp.int32(config.substeps))
    vel, cimp = restitution(layout, loop.const, cimp, vel, loop.vel0, gap, loop.h, loop.restitution_threshold,
                            colours, config.impact_sweeps, config.bounce_sweeps)
    def rejoin(pose, vel):  # the joint projection: velocities, and positions when configured
        if config.joint_projection is None:
            return pose, vel
        frame = joint_solver.frame(loop.joints, loop.jc, pose)
        vel, shift = joint_solver.project(loop.jc, frame, vel, config.joint_projection / (config.substeps * loop.h),
                                          joints, config.joint_position_projection)
        return (pose if shift is None else Pose(pose.x + shift.x, pose.y + shift.y, pose.a + shift.a)), vel

    pose, vel = rejoin(pose, vel)
    if config.static_walls:  # nothing gets into or through a static body: continuous collision, then the push-out
        pose = static_walls.sweep_back(loop.walls, loop.joints, loop.pose0, pose, _linked)
        pose = static_walls.push_out(layout, loop.cc, loop.const, cimp, colours, pose, vel, loop.pose0,
                                     loop.linear_slop, rejoin)
    return pose, vel, cimp, jimp


def _linked(joints: Joints, M: int):
    """(M, M, *batch) joint_connected for batch-last joints (every leaf's last axes are the batch)."""
    per_scene = functools.partial(joint_connected, M=M)
    for _ in range(joints.a.ndim - 1):
        per_scene = jax.vmap(per_scene, in_axes=-1, out_axes=-1)
    return per_scene(joints)


def _step_chunk_broad(layout: ContactLayout, states: SimState, params: SimParams, motor_actions, thruster_actions,
                      config: SolverConfig):
    """_step_chunk for big scenes: the narrow phase and the sweeps visit only the candidate pairs of the
    broad phase, coloured in the step (jax2d.broad_phase); results go back to the persistent slots."""
    M, S = layout.num_padded, layout.num_slots
    B = states.bodies.active.shape[0]
    last = functools.partial(jax.tree.map, lambda x: jnp.moveaxis(x, 0, -1))
    first = functools.partial(jax.tree.map, lambda x: jnp.moveaxis(x, -1, 0))
    scene = last(states)
    rows, colours, width = broad_phase.rows_for(layout)
    total = colours * width
    may_collide = pair_filter(layout, scene.bodies, jnp.zeros((S, B), bool), M)
    reach = step_reach(scene, params.dt)
    cand = broad_phase.candidates(layout, scene.bodies, params.speculative_distance, may_collide, total - rows, reach)
    manifold = broad_phase.narrow_phase(cand, scene.bodies, params.speculative_distance,
                                        functools.partial(_over_pairs_and_batch, batch=(B,)), total, reach)
    # The joint closure only where some scene has a joint: (M, M) matrix products are costly at M ~ 200.
    jointed = jax.lax.cond(
        jnp.any(states.joints.active),
        lambda: jax.vmap(lambda j, a, b: joint_connected(j, M)[a, b])(states.joints, cand.slot_a.T, cand.slot_b.T),
        lambda: jnp.zeros((B, total), bool))
    # Each scene's old contacts of its candidates (padding rows: slot S, out of range, filled with 0).
    contacts = jax.tree.map(lambda x: take_rows(x, cand.slot, fill=0), scene.contacts)
    contacts = dataclasses.replace(contacts, key=jnp.where(cand.slot[:, None] < S, contacts.key, -1))
    scene = dataclasses.replace(scene, contacts=contacts)
    loop, valid, solved = _prepare(cand, scene, params, last(motor_actions), last(thruster_actions), manifold,
                                   last(jointed), reach, config)
    pose, vel, cimp, jimp = _solve(solved, loop, config)
    cimp = contact_solver.unpack_impulses(solved, cimp)  # per-scene solve order: unpacked batch-last
    pose, vel, cimp, jimp, manifold, valid, dyn = first((pose, vel, cimp, jimp, manifold, valid, loop.dyn))

    def to_slots(x, fill):  # (B, L, 2) candidate rows -> (B, S, 2) slots, by each scene's slots; padding dropped
        return jax.vmap(lambda x, slot: jnp.full((S,) + x.shape[1:], fill, x.dtype).at[slot].set(x, mode="drop"))(
            x, cand.slot.T)

    manifold = Manifold(None, None, to_slots(manifold.separation, 0.0), to_slots(manifold.key, -1),
                        to_slots(manifold.valid, False))
    valid = to_slots(valid, False)
    cimp = contact_solver.ContactImpulses(*(to_slots(x, 0.0) for x in cimp))
    return jax.vmap(_store)(states, params, pose, vel, cimp, jimp, manifold, valid, dyn)


@functools.cache
def _vmappable(config: SolverConfig):
    """`step` for one config: one scene as a batch of one, and a vmap rule that calls step_batch."""

    @custom_vmap
    def one(state, params, motor_actions, thruster_actions):
        batch = jax.tree.map(lambda x: jnp.asarray(x)[None], (state, motor_actions, thruster_actions))
        out = step_batch(batch[0], params, batch[1], batch[2], config)
        return jax.tree.map(lambda x: x[0], out)

    @one.def_vmap
    def rule(axis_size, in_batched, state, params, motor_actions, thruster_actions):
        def spread(tree, batched):  # give every unbatched leaf the batch axis
            return jax.tree.map(lambda x, b: x if b else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x)),
                                tree, batched)

        state_b, params_b, motor_b, thrust_b = in_batched
        out = step_batch(spread(state, state_b), spread(params, params_b), spread(motor_actions, motor_b),
                         spread(thruster_actions, thrust_b), config)
        return out, jax.tree.map(lambda _: True, out)

    return one


class LoopData(NamedTuple):
    """What the substeps read and carry, per scene (batch-last inside the loop)."""

    dyn: jax.Array  # (M,) 1 for moving bodies
    inv_mass: jax.Array
    inv_inertia: jax.Array
    pose0: Pose
    vel0: Vel
    joints: Joints  # anchors and reference angles for the joint frames
    jc: joint_solver.JointConstraints
    cc: contact_solver.ContactConstraints
    const: jax.Array  # packed contact constraints (C, F, K)
    cimp: jax.Array  # packed warm-start impulses (C, 6, K)
    jimp: jax.Array  # (J, 6)
    forces: tuple
    gravity: jax.Array  # (2,)
    h: jax.Array  # substep
    contact_softness: Softness
    joint_softness: Softness
    max_push_velocity: jax.Array
    restitution_threshold: jax.Array
    linear_slop: jax.Array
    walls: static_walls.Shapes  # for the sweep back


def _prepare(layout: ContactLayout, state: SimState, params: SimParams, motor_actions, thruster_actions,
             manifold: Manifold, jointed, reach, config: SolverConfig) -> tuple[LoopData, jax.Array, ContactLayout]:
    """Constraint preparation from the pose at the start of the step, on batch-last arrays.

    Every leaf has the batch as its last axis: per body (N, *batch), per slot (S, *batch),
    params (*batch). Run batch-major under vmap, this stage gathered a few floats per row and
    then transposed every constraint array for the substeps; batch-last, each gather by a
    constant slot index is one contiguous row. jointed: (S, *batch) slots whose bodies a chain
    of joints connects; reach: (N, *batch) step_reach, as the narrow phase used it. Returns the loop
    data, (S, 2, *batch) which points are valid and the layout the solver uses (for
    broad_phase.Candidates, a broad_phase.DynamicLayout coloured here).
    """
    M = layout.num_padded
    b = state.bodies
    dynamic = b.active & (b.inv_mass > 0)
    inv_mass = _pad(jnp.where(dynamic, b.inv_mass, 0.0), M)
    inv_inertia = _pad(jnp.where(dynamic, b.inv_inertia, 0.0), M)
    dyn = _pad(dynamic.astype(jnp.float32), M)
    pose0 = Pose(_pad(b.position[:, 0], M), _pad(b.position[:, 1], M), _pad(b.angle, M))
    vel = Vel(_pad(b.velocity[:, 0], M) * dyn, _pad(b.velocity[:, 1], M) * dyn, _pad(b.angular_velocity, M) * dyn)

    h = params.dt / config.substeps
    inv_h = 1.0 / h
    jc = joint_solver.prepare(state.joints, M, inv_mass, inv_inertia, motor_actions, h, params)
    enabled = pair_filter(layout, b, jointed, M)
    valid = manifold.valid & enabled[:, None]
    if isinstance(layout, broad_phase.Candidates):
        # Colour the pairs that hold a point in some scene; bodies static in every scene may repeat.
        live = jnp.any(valid, axis=1)  # (L, B)
        shareable = dyn == 0.0  # (M, B)
        rows = layout.slot.shape[0]
        layout, placed = broad_phase.colour(layout, live, shareable, M, broad_phase.MAX_COLOURS,
                                            rows // broad_phase.MAX_COLOURS)
        valid = valid & placed[:, None]  # (L, 2, B) & (L, 1, B)
    cc = contact_solver.prepare(layout, manifold, valid, pose0, vel, inv_mass, inv_inertia,
                                _pad(b.friction, M), _pad(b.restitution, M), state.gravity, h)
    cimp = contact_solver.pack_impulses(layout, _matched_impulses(state.contacts, manifold.key, valid,
                                                                  config.warm_start))
    loop = LoopData(
        dyn=dyn, inv_mass=inv_mass, inv_inertia=inv_inertia, pose0=pose0, vel0=vel,
        joints=state.joints, jc=jc, cc=cc,
        const=contact_solver.pack_constraints(layout, cc),
        cimp=cimp,
        jimp=state.joints.impulse if config.warm_start else jnp.zeros_like(state.joints.impulse),
        forces=thruster_forces(state.thrusters, thruster_actions, M, params),
        gravity=state.gravity,
        h=jnp.asarray(h, jnp.float32),
        contact_softness=soft(jnp.minimum(params.contact_hertz, 0.25 * inv_h), params.contact_damping_ratio, h),
        joint_softness=soft(params.joint_hertz, params.joint_damping_ratio, h),
        max_push_velocity=jnp.asarray(params.max_push_velocity, jnp.float32),
        restitution_threshold=jnp.asarray(params.restitution_threshold, jnp.float32),
        linear_slop=jnp.asarray(params.linear_slop, jnp.float32),
        walls=static_walls.shapes(b, reach, params.speculative_distance, M),
    )
    return loop, valid, layout


def _substeps(layout: ContactLayout, d: LoopData, colours: contact_solver.Schedule, joints: joint_solver.Schedule,
              config: SolverConfig):
    """The substep loop on batch-last arrays: every function here broadcasts over trailing batch axes.

    colours: the colours with a point in some scene (contact_solver.schedule); joints: the joint
    slots active in some scene (joint_solver.schedule), which the joint loops visit.
    """
    h = d.h
    inv_h = 1.0 / h

    def substep(i, carry):
        pose, vel, cimp, jimp = carry
        vel = integrate_velocities(vel, pose, d.dyn, d.inv_mass, d.inv_inertia, d.gravity, d.forces, h)
        frame = joint_solver.frame(d.joints, d.jc, pose)
        vel = joint_solver.warm_start(d.jc, frame, jimp, vel, plan=joints)
        vel = contact_solver.warm_start(layout, d.const, cimp, vel, plan=colours)
        vel, jimp = joint_solver.solve(d.jc, frame, jimp, vel, d.joint_softness, inv_h, use_bias=True, plan=joints)
        sep = contact_solver.current_separation(layout, d.cc, pose, d.pose0, i)
        vel, cimp = contact_solver.solve(layout, d.const, cimp, vel, sep, d.contact_softness, inv_h,
                                         d.max_push_velocity, use_bias=True, plan=colours)
        pose = Pose(pose.x + h * vel.x, pose.y + h * vel.y, pose.a + h * vel.w)
        frame = joint_solver.frame(d.joints, d.jc, pose)
        sep = contact_solver.current_separation(layout, d.cc, pose, d.pose0, i)
        for _ in range(config.relax_iterations):
            vel, jimp = joint_solver.solve(d.jc, frame, jimp, vel, d.joint_softness, inv_h, use_bias=False,
                                           plan=joints)
            vel, cimp = contact_solver.solve(layout, d.const, cimp, vel, sep, d.contact_softness, inv_h,
                                             d.max_push_velocity, use_bias=False, plan=colours)
        return pose, vel, cimp, jimp

    return jax.lax.fori_loop(0, config.substeps, substep, (d.pose0, d.vel0, d.cimp, d.jimp))


def _pad(x, m):
    """Append static dummy rows (axis 0) so the body count is M."""
    return jnp.pad(x, [(0, m - x.shape[0])] + [(0, 0)] * (x.ndim - 1))


def step_reach(state: SimState, dt):
    """(N, *batch) how far any point of each body can move in one step, batch-last: its speed, its spin times
    its farthest point, and gravity's gain, over dt. See narrow_phase: the speculative margin of a pair is the
    sum of its bodies' reaches on top of SimParams.speculative_distance."""
    b = state.bodies
    extent = jnp.concatenate([jnp.max(jnp.linalg.norm(b.vertices, axis=-2), axis=1), b.radius])
    speed = jnp.linalg.norm(b.velocity, axis=1)
    gain = jnp.linalg.norm(state.gravity, axis=0) * dt
    return dt * (speed + jnp.abs(b.angular_velocity) * extent + gain)


def narrow_phase(layout: ContactLayout, b: Bodies, speculative, reach=None) -> Manifold:
    """Manifolds for every slot, batch-last: each kind of pair is evaluated on its own constant index list.

    b: bodies with the batch as the last axis of every leaf; speculative: (*batch); reach: None or (N, *batch)
    how far each body can move in this step (step_reach).

    A pair's points are kept while their separation is below the speculative distance plus both bodies'
    reach, so a contact exists before any body can cross the gap in one step, however fast it moves (up to
    the speed clamp): the solver removes only the approaching velocity beyond the gap (s / h), so a far
    point costs nothing but its solve. Without the reach, a 0.1 m ball at 30 m/s passed through a 0.1 m
    wall in 4 of 5 tries.
    Returns manifold fields with the batch last, e.g. normal (S, 2, B). The collide functions
    are written for one pair; they map over the batch as the minor axis (each of a polygon's
    V edges is then a row of B scenes) and over the pairs as the major one. With the pairs
    minor (a vmap of the per-scene narrow phase), XLA's loops ran over rows of V = 8 floats
    and the stage took twice as long at s, batch 2048.
    """
    P = b.vertices.shape[0]
    pos, ang, verts, nv, rad = b.position, b.angle, b.vertices, b.n_vertices, b.radius
    batch = pos.shape[2:]
    over_pairs_and_batch = functools.partial(_over_pairs_and_batch, batch=batch)
    spec = jnp.broadcast_to(jnp.asarray(speculative, jnp.float32), batch)
    reach = jnp.zeros((b.active.shape[0],) + batch, jnp.float32) if reach is None else reach

    def margin(i, j):
        return spec + reach[i] + reach[j]

    kinds = layout.by_kind
    parts = []
    i, j = layout.slot_a[kinds[POLY_POLY]], layout.slot_b[kinds[POLY_POLY]]
    if len(i):
        parts.append(over_pairs_and_batch(collide_polygons, 8)(
            pos[i], ang[i], verts[i], nv[i], pos[j], ang[j], verts[j], nv[j], margin(i, j)))
    # Polygon-circle pairs in either order share one call; circle-first pairs flip the normal.
    pc, cp = kinds[POLY_CIRCLE], kinds[CIRCLE_POLY]
    poly = np.concatenate([layout.slot_a[pc], layout.slot_b[cp]])
    circle = np.concatenate([layout.slot_b[pc], layout.slot_a[cp]])
    if len(poly):
        m = over_pairs_and_batch(collide_polygon_circle, 6)(
            pos[poly], ang[poly], verts[poly], nv[poly], pos[circle], rad[circle - P], margin(poly, circle))
        sign = np.concatenate([np.ones(len(pc)), -np.ones(len(cp))]).astype(np.float32)
        parts.append(dataclasses.replace(m, normal=m.normal * sign.reshape((-1, 1) + (1,) * len(batch))))
    i, j = layout.slot_a[kinds[CIRCLE_CIRCLE]], layout.slot_b[kinds[CIRCLE_CIRCLE]]
    if len(i):
        parts.append(over_pairs_and_batch(collide_circles, 4)(pos[i], rad[i - P], pos[j], rad[j - P], margin(i, j)))
    S = layout.num_slots
    # The row padding slots take: no point, normal (0, 1).
    empty = Manifold(jnp.array([[0.0, 1.0]]), jnp.zeros((1, 2, 2)), jnp.zeros((1, 2)),
                     jnp.full((1, 2), -1, jnp.int32), jnp.zeros((1, 2), bool))
    empty = jax.tree.map(lambda x: jnp.broadcast_to(x.reshape(x.shape + (1,) * len(batch)), x.shape + batch), empty)
    if not parts:
        return jax.tree.map(lambda x: jnp.repeat(x, S, axis=0), empty)
    rows = jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts, empty)
    # Every slot picks its row with a constant index (padding slots take the empty row).
    return jax.tree.map(lambda x: x[layout.gather], rows)


def _over_pairs_and_batch(collide, n: int, batch: tuple):
    """A collide function of n pair arguments plus the pair's speculative margin, mapped over the batch
    axes (minor, innermost last) and the pairs (major)."""
    inner = collide
    for _ in batch:
        inner = jax.vmap(inner, in_axes=(-1,) * (n + 1), out_axes=-1)
    return jax.vmap(inner, in_axes=(0,) * (n + 1))


def pair_filter(layout: ContactLayout, b: Bodies, jointed, M: int):
    """(S, *batch) whether each slot's bodies may collide: active, not both static, modes agree, not jointed."""
    a, c = layout.slot_a, layout.slot_b  # (S,), or (S, B): each scene's own pairs (broad_phase)
    ta, tc = functools.partial(take_rows, idx=a), functools.partial(take_rows, idx=c)
    active = _pad(b.active, M)
    moving = _pad(b.active & (b.inv_mass > 0), M)
    mode = _pad(b.collision_mode, M)
    real = layout.slot_kind != PADDING
    if real.ndim == 1:
        real = real.reshape((-1,) + (1,) * (active.ndim - 1))
    return real & ta(active) & tc(active) & (ta(moving) | tc(moving)) & modes_agree(ta(mode), tc(mode)) & ~jointed


def joint_connected(joints: Joints, M: int):
    """(M, M) bool for one scene: bodies linked through any chain of joints (transitive closure by squaring)."""
    on = joints.active.astype(jnp.float32)[:, None]
    link = (jax.nn.one_hot(joints.a, M) * on).T @ (jax.nn.one_hot(joints.b, M) * on)
    reach = (jnp.eye(M) + link + link.T) > 0
    for _ in range(max(1, math.ceil(math.log2(M)))):
        r = reach.astype(jnp.float32)
        reach = (r @ r) > 0
    return reach


def _matched_impulses(old: Contacts, key, valid, warm_start: bool) -> contact_solver.ContactImpulses:
    """Last step's impulses for points whose feature key is unchanged (either slot), else 0."""
    zeros = jnp.zeros(key.shape, jnp.float32)
    if not warm_start:
        return contact_solver.ContactImpulses(zeros, zeros, zeros)
    same = (key == old.key) & old.active
    swapped = (key == old.key[:, ::-1]) & old.active[:, ::-1]

    def pick(x):
        return jnp.where(valid, jnp.where(same, x, jnp.where(swapped, x[:, ::-1], 0.0)), 0.0)

    return contact_solver.ContactImpulses(pick(old.normal_impulse), pick(old.tangent_impulse), zeros)


def thruster_forces(t: Thrusters, actions, M: int, params: SimParams):
    """Per-thruster selection rows (T, M, *batch) and force magnitudes; directions follow the body each substep."""
    sel = one_hot_rows(t.body, M) * t.active.astype(jnp.float32)[:, None]
    magnitude = t.power * params.base_thruster_power * jnp.clip(actions, 0.0, 1.0)
    return sel, magnitude, t


def integrate_velocities(vel: Vel, pose: Pose, dyn, inv_mass, inv_inertia, gravity, forces, h) -> Vel:
    sel, magnitude, t = forces
    body_angle = pick_rows(sel, pose.a)
    fx, fy = rotate(jnp.cos(body_angle + t.angle), jnp.sin(body_angle + t.angle), magnitude, 0.0)
    rx, ry = rotate(jnp.cos(body_angle), jnp.sin(body_angle), t.anchor[:, 0], t.anchor[:, 1])
    # Sum thruster by thruster, in slot order: a reduction could add them in another
    # order under vmap and break bitwise batch equality.
    force_x, force_y, torque = jnp.zeros_like(vel.x), jnp.zeros_like(vel.x), jnp.zeros_like(vel.x)
    for t_i in range(sel.shape[0]):
        force_x = force_x + fx[t_i] * sel[t_i]
        force_y = force_y + fy[t_i] * sel[t_i]
        torque = torque + (rx[t_i] * fy[t_i] - ry[t_i] * fx[t_i]) * sel[t_i]
    return Vel(
        vel.x + h * (dyn * gravity[0] + inv_mass * force_x),
        vel.y + h * (dyn * gravity[1] + inv_mass * force_y),
        vel.w + h * inv_inertia * torque,
    )


def _store(state: SimState, params: SimParams, pose: Pose, vel: Vel, cimp, jimp, manifold, valid, dyn) -> SimState:
    """Write the result back, clamped; a body whose result is not finite keeps its old pose and stops.

    The new state's `frozen` counts those bodies: the guard keeps NaN out of the scene, so without the
    count a test that looks for NaN could not see that it fired.
    """
    b = state.bodies
    N = b.active.shape[0]
    vx, vy, w = vel.x[:N], vel.y[:N], vel.w[:N]
    speed = jnp.sqrt(vx * vx + vy * vy)
    scale = jnp.where(speed > params.max_linear_speed, params.max_linear_speed / jnp.maximum(speed, 1e-6), 1.0)
    vx, vy = vx * scale, vy * scale
    w = jnp.clip(w, -params.max_angular_speed, params.max_angular_speed)
    x = jnp.clip(pose.x[:N], -params.max_position, params.max_position)
    y = jnp.clip(pose.y[:N], -params.max_position, params.max_position)
    a = pose.a[:N]
    moving = dyn[:N] > 0
    ok = moving & jnp.isfinite(vx) & jnp.isfinite(vy) & jnp.isfinite(w) & jnp.isfinite(x) & jnp.isfinite(y) \
        & jnp.isfinite(a)
    position = jnp.where(ok[:, None], jnp.stack([x, y], axis=1), b.position)
    bodies = dataclasses.replace(
        b,
        position=position,
        angle=jnp.where(ok, a, b.angle),
        velocity=jnp.where(ok[:, None], jnp.stack([vx, vy], axis=1), 0.0),
        angular_velocity=jnp.where(ok, w, 0.0),
    )
    finite = lambda z: jnp.where(jnp.isfinite(z), z, 0.0)  # noqa: E731
    joints = dataclasses.replace(state.joints, impulse=finite(jimp))
    contacts = Contacts(
        normal_impulse=finite(cimp.normal),
        tangent_impulse=finite(cimp.tangent),
        key=jnp.where(valid, manifold.key, -1),
        active=valid,
        separation=jnp.where(valid, finite(manifold.separation), 0.0),
    )
    frozen = jnp.sum(moving & ~ok, dtype=jnp.int32)
    return SimState(bodies, joints, state.thrusters, contacts, state.gravity, frozen)
