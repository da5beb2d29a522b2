"""One physics step, as a pipeline of stages (Box2D v3's soft step); each stage's module in brackets.

    narrow phase            contact manifolds for every pair slot, once per step, with a margin of the
                            bodies' reach in the step (narrow_phase); in big scenes only for each scene's
                            candidate pairs (broad_phase.find)
    prepare                 contact and joint constraints, warm-start impulses matched by feature key
                            (contact_solver.prepare, joint_solver.prepare; big scenes coloured here)
    substeps x n:
        integrate velocities    gravity and thrusters (forces)
        warm start              last impulses, applied all at once
        solve                   joints then contacts, with soft position bias (joint_solver, contact_solver), the
                                contacts' pass chained with 2 more over those stiffened by their resting load
                                (loads.py, sweeps.Chain)
        integrate positions
        relax                   joints then contacts, without bias (removes bias energy), chained with 1 more
                                pass over the stiffened contacts
    restitution             impacts propagated through touching chains, then bounces (restitution)
    joint projection        all joints' point and weld rows solved at once, on velocities and positions
                            (joint_solver.project)
    static walls            fast bodies swept back to where they enter another body; bodies pushed out of
                            static ones beyond 2 slops, alternating with the projection; the sweep back again,
                            also for centres that went through a polygon; a centre still inside a polygon
                            (static or dynamic) taken out the way it came, with its assembly (static_walls)
    store                   impulses for the next step; clamp and NaN guard (store; SimState.frozen counts
                            the bodies it froze)

Each stage of step_batch runs under a `jax.named_scope` (jax2d_narrow_phase, jax2d_prepare, jax2d_substeps,
jax2d_restitution, jax2d_joint_projection, jax2d_static_walls, jax2d_store; jax2d_broad_phase in big scenes):
the compiled program's op names carry them, so a profile can count kernels and time per stage.
The contact passes all run on the colour sweep of sweeps.py. Inside the step every body quantity is
its own array over M padded bodies (math2d.Vel / Pose); M is the body count rounded up to even, the
extra body a static dummy that padding contact slots point at. Every stage but the store runs on a
batch of scenes with the batch as the last axis, (M, B) per body (see step_batch).
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax.custom_batching import custom_vmap

from jax2d import broad_phase, contact_solver, control, joint_solver, static_walls
from jax2d.collide import Manifold
from jax2d.compact import Compact, unpack, update
from jax2d.forces import integrate_velocities, thruster_forces
from jax2d.math2d import Pose, Softness, Vel, pad_rows, soft
from jax2d.narrow_phase import joint_labels, narrow_phase, pair_filter, step_reach
from jax2d.pairs import ContactLayout, contact_layout
from jax2d.restitution import restitution
from jax2d.state import Joints, SimParams, SimState, SolverConfig
from jax2d.store import store
from jax2d.sweeps import Chain, Schedule, chain, schedule

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
    return control.per_platform(in_parts, whole, states, params, motor_actions, thruster_actions)


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
    with jax.named_scope("jax2d_narrow_phase"):
        group = jax.vmap(lambda j: joint_labels(j, M))(states.joints)  # (B, M) each body's joint group
        jointed = group[:, layout.slot_a] == group[:, layout.slot_b]  # joint_connected at the slots' pairs
        scene = _last(states)
        reach = step_reach(scene, params.dt)
        manifold = narrow_phase(layout, scene.bodies, params.speculative_distance, reach, _token(scene, config))
    with jax.named_scope("jax2d_prepare"):
        loop, valid, _ = _prepare(layout, scene, params, _last(motor_actions), _last(thruster_actions), manifold,
                                  _last(jointed), _last(group), reach, config)
    pose, vel, cimp, jimp = _solve(layout, loop, config)
    with jax.named_scope("jax2d_store"):
        pose, vel, cimp, jimp, manifold, valid, dyn = _first((pose, vel, cimp, jimp, manifold, valid, loop.dyn))
        cimp = jax.vmap(functools.partial(contact_solver.unpack_impulses, layout))(cimp)
        return jax.vmap(store)(states, params, pose, vel, cimp, jimp, manifold, valid, dyn)


def _step_chunk_broad(layout: ContactLayout, states: SimState, params: SimParams, motor_actions, thruster_actions,
                      config: SolverConfig):
    """_step_chunk for big scenes: the narrow phase and the sweeps visit only the candidate pairs of the
    broad phase, coloured in the step (jax2d.broad_phase); results go back to the persistent slots."""
    S = layout.num_slots
    scene = _last(states)
    reach = step_reach(scene, params.dt)
    with jax.named_scope("jax2d_broad_phase"):
        found = broad_phase.find(layout, scene, states.joints, params.speculative_distance, reach)
    scene = dataclasses.replace(scene, contacts=found.contacts)
    loop, valid, solved = _prepare(found.cand, scene, params, _last(motor_actions), _last(thruster_actions),
                                   found.manifold, found.jointed, found.group, reach, config)
    pose, vel, cimp, jimp = _solve(solved, loop, config)
    cimp = contact_solver.unpack_impulses(solved, cimp)  # per-scene solve order: unpacked batch-last
    pose, vel, cimp, jimp, manifold, valid, dyn = _first((pose, vel, cimp, jimp, found.manifold, valid, loop.dyn))
    to_slots = functools.partial(broad_phase.to_slots, found.cand, S)
    manifold = Manifold(None, None, to_slots(manifold.separation, 0.0), to_slots(manifold.key, -1),
                        to_slots(manifold.valid, False))
    valid = to_slots(valid, False)
    cimp = contact_solver.ContactImpulses(*(to_slots(x, 0.0) for x in cimp))
    return jax.vmap(store)(states, params, pose, vel, cimp, jimp, manifold, valid, dyn)


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
             manifold: Manifold, jointed, group, reach,
             config: SolverConfig) -> tuple[LoopData, jax.Array, ContactLayout]:
    """Constraint preparation from the pose at the start of the step, on batch-last arrays.

    Every leaf has the batch as its last axis: per body (N, *batch), per slot (S, *batch),
    params (*batch). Run batch-major under vmap, this stage gathered a few floats per row and
    then transposed every constraint array for the substeps; batch-last, each gather by a
    constant slot index is one contiguous row. jointed: (S, *batch) slots whose bodies a chain
    of joints connects; group: (M, *batch) the bodies' joint groups (narrow_phase.joint_labels); reach: (N, *batch)
    step_reach, as the narrow phase used it. Returns the loop
    data, (S, 2, *batch) which points are valid and the layout the solver uses (for
    broad_phase.Candidates, a broad_phase.DynamicLayout coloured here).
    """
    M = layout.num_padded
    b = state.bodies
    dynamic = b.active & (b.inv_mass > 0)
    inv_mass = pad_rows(jnp.where(dynamic, b.inv_mass, 0.0), M)
    inv_inertia = pad_rows(jnp.where(dynamic, b.inv_inertia, 0.0), M)
    dyn = pad_rows(dynamic.astype(jnp.float32), M)
    pose0 = Pose(pad_rows(b.position[:, 0], M), pad_rows(b.position[:, 1], M), pad_rows(b.angle, M))
    vel = Vel(pad_rows(b.velocity[:, 0], M) * dyn, pad_rows(b.velocity[:, 1], M) * dyn,
              pad_rows(b.angular_velocity, M) * dyn)

    h = params.dt / config.substeps
    inv_h = 1.0 / h
    jc = joint_solver.prepare(state.joints, M, inv_mass, inv_inertia, motor_actions, h, params)
    enabled = pair_filter(layout, b, jointed, M)
    valid = manifold.valid & enabled[:, None]
    if isinstance(layout, broad_phase.Candidates):
        # Colour the pairs that hold a point in some scene; bodies static in every scene may repeat.
        live = jnp.any(valid, axis=1)  # (L, B)
        shareable = dyn == 0.0  # (M, B)
        layout, placed = broad_phase.colour(layout, live, shareable, M)
        valid = valid & placed[:, None]  # (L, 2, B) & (L, 1, B)
    warm = contact_solver.matched_impulses(state.contacts, manifold.key, valid, config.warm_start)
    contact_softness = soft(jnp.minimum(params.contact_hertz, 0.25 * inv_h), params.contact_damping_ratio, h)
    cc = contact_solver.prepare(layout, manifold, valid, pose0, vel, inv_mass, inv_inertia,
                                pad_rows(b.friction, M), pad_rows(b.restitution, M), state.gravity, h,
                                contact_softness, params.linear_slop)
    cimp = contact_solver.pack_impulses(layout, contact_solver.seed_impulses(warm, cc) if config.warm_start else warm)
    loop = LoopData(
        dyn=dyn, inv_mass=inv_mass, inv_inertia=inv_inertia, pose0=pose0, vel0=vel,
        joints=state.joints, jc=jc, cc=cc,
        const=contact_solver.pack_constraints(layout, cc),
        cimp=cimp,
        jimp=state.joints.impulse if config.warm_start else jnp.zeros_like(state.joints.impulse),
        forces=thruster_forces(state.thrusters, thruster_actions, M, params),
        gravity=state.gravity,
        h=jnp.asarray(h, jnp.float32),
        contact_softness=contact_softness,
        joint_softness=soft(params.joint_hertz, params.joint_damping_ratio, h),
        max_push_velocity=jnp.asarray(params.max_push_velocity, jnp.float32),
        restitution_threshold=jnp.asarray(params.restitution_threshold, jnp.float32),
        linear_slop=jnp.asarray(params.linear_slop, jnp.float32),
        walls=static_walls.shapes(b, group, reach, params.speculative_distance, M),
    )
    return loop, valid, layout


def _substeps(layout: ContactLayout, d: LoopData, solve_plan: Schedule | Chain, relax_plan: Schedule | Chain,
              colours: Schedule, joints: joint_solver.Schedule, config: SolverConfig):
    """The substep loop on batch-last arrays: every function here broadcasts over trailing batch axes.

    colours: the colours with a point in some scene (contact_solver.schedule); solve_plan and relax_plan: the
    contact solve's and the last relax's colours, chained with more passes over those with a point stiffened by
    its load (_contact_plans); joints: the joint slots active in some scene (joint_solver.schedule), which the joint
    loops visit.
    """
    h = d.h
    inv_h = 1.0 / h
    fixed = config.control_flow == control.FIXED

    def substep(i, carry):
        pose, vel, cimp, jimp = carry
        token = None if fixed else i  # math2d.stored
        vel = integrate_velocities(vel, pose, d.dyn, d.inv_mass, d.inv_inertia, d.gravity, d.forces, h)
        frame = joint_solver.frame(d.joints, d.jc, pose)
        vel = joint_solver.warm_start(d.jc, frame, jimp, vel, plan=joints)
        vel = contact_solver.warm_start(layout, d.const, cimp, vel, plan=colours)
        vel, jimp = joint_solver.solve(d.jc, frame, jimp, vel, d.joint_softness, inv_h, use_bias=True, plan=joints)
        sep = contact_solver.current_separation(layout, d.cc, pose, d.pose0, token)
        vel, cimp = contact_solver.solve(layout, d.const, cimp, vel, sep, d.contact_softness, inv_h,
                                         d.max_push_velocity, use_bias=True, plan=solve_plan)
        pose = Pose(pose.x + h * vel.x, pose.y + h * vel.y, pose.a + h * vel.w)
        frame = joint_solver.frame(d.joints, d.jc, pose)
        sep = contact_solver.current_separation(layout, d.cc, pose, d.pose0, token)
        for r in range(config.relax_iterations):
            vel, jimp = joint_solver.solve(d.jc, frame, jimp, vel, d.joint_softness, inv_h, use_bias=False,
                                           plan=joints)
            vel, cimp = contact_solver.solve(layout, d.const, cimp, vel, sep, d.contact_softness, inv_h,
                                             d.max_push_velocity, use_bias=False,
                                             plan=relax_plan if r == config.relax_iterations - 1 else colours)
        return pose, vel, cimp, jimp

    return jax.lax.fori_loop(0, config.substeps, substep, (d.pose0, d.vel0, d.cimp, d.jimp))


def _contact_plans(const, colours: Schedule, config: SolverConfig) -> tuple[Schedule | Chain, Schedule | Chain]:
    """The contact solve's and the last relax's plans: a pass over the live colours, chained with the extra passes
    over the points stiffened by their load (contact_solver.load_softness) that the config asks for.

    Those passes make the velocities the positions are integrated with hold a heavy body on a light one, which a
    pass over all colours does only by about the mass ratio; every other one takes a manifold's second point first
    (point 0 first in every pass pushed a box between two stiff manifolds to one side each time). Chained to the
    pass over all colours (sweeps.Chain), they are one loop after it, with no visit in steps that have no
    stiffened point."""
    stiff = schedule(const, colours.fixed, rows="stiff")

    def plan(repeats: int):
        return chain(colours, stiff, repeats) if repeats else colours

    return plan(config.stiff_solve_iterations), plan(config.stiff_relax_iterations)


def _solve(layout, loop: LoopData, config: SolverConfig):
    """Substeps, restitution, the joint projection and the static walls on the prepared loop data (batch-last)."""
    fixed = config.control_flow == control.FIXED
    with jax.named_scope("jax2d_substeps"):
        colours = schedule(loop.const, fixed)
        solve_plan, relax_plan = _contact_plans(loop.const, colours, config)
        joints = joint_solver.schedule(loop.jc, fixed)
        pose, vel, cimp, jimp = _substeps(layout, loop, solve_plan, relax_plan, colours, joints, config)
    with jax.named_scope("jax2d_restitution"):
        gap = functools.partial(contact_solver.current_separation, layout, loop.cc, pose, loop.pose0,
                                None if fixed else jnp.int32(config.substeps))
        vel, cimp = restitution(layout, loop.const, cimp, vel, loop.vel0, gap, loop.h, loop.restitution_threshold,
                                colours, config.impact_sweeps, config.bounce_sweeps)

    def rejoin(pose, vel):  # the joint projection: velocities, and positions when configured
        if config.joint_projection is None:
            return pose, vel
        frame = joint_solver.frame(loop.joints, loop.jc, pose)
        vel, shift = joint_solver.project(loop.jc, frame, vel, config.joint_projection / (config.substeps * loop.h),
                                          joints, config.joint_position_projection)
        return (pose if shift is None else Pose(pose.x + shift.x, pose.y + shift.y, pose.a + shift.a)), vel

    with jax.named_scope("jax2d_joint_projection"):
        pose, vel = rejoin(pose, vel)
    if config.static_walls:  # nothing gets into or through a static body: continuous collision, then the push-out
        with jax.named_scope("jax2d_static_walls"):
            pose = static_walls.sweep_back(loop.walls, loop.pose0, pose, fixed)
            pose = static_walls.push_out(layout, loop.cc, loop.const, cimp, colours, pose, vel, loop.pose0,
                                         loop.linear_slop, rejoin)
            # Again: the push-out's joint projections move bodies too, and one that had no contact with a wall at
            # the step's start has no point to be pushed out by (crowded scene 58, actions key 4, step 1063: a light
            # triangle welded to a motor hub went from 15 cm above the floor to 3.5 cm into it).
            # and last, a centre still inside a polygon goes out the way it came (static_walls.centre_out)
            pose = static_walls.sweep_back_then_centre_out(loop.walls, loop.pose0, pose, loop.linear_slop, fixed,
                                                           config.num_static, None if fixed else colours.count)
    return pose, vel, cimp, jimp


def _token(scene: SimState, config: SolverConfig):
    """A traced non-negative integer for math2d.stored before any loop index exists (XLA folds a constant one,
    and with it the conditional that stores); None with fixed control flow (jax2d/control.py)."""
    if config.control_flow == control.FIXED or not scene.bodies.n_vertices.size:  # (no polygons: nothing to store)
        return None
    return jnp.maximum(scene.bodies.n_vertices.reshape(-1)[0], 0)


def _last(tree):
    """Every leaf with its leading (batch) axis moved last."""
    return jax.tree.map(lambda x: jnp.moveaxis(x, 0, -1), tree)


def _first(tree):
    """Every leaf with its last (batch) axis moved first."""
    return jax.tree.map(lambda x: jnp.moveaxis(x, -1, 0), tree)
