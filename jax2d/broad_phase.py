"""Broad phase and per-step colouring for big scenes (SolverConfig.broad_phase).

The all-pairs path (pairs.py) gives every body pair a persistent slot, runs the narrow phase on
every slot and sweeps every colour that holds a point. A 210-box pyramid has 22,366 slots in 211
colours, and its ~600 touching pairs fall in all 211 of them: a step at batch 1 took 73-109 ms, of
which the narrow phase was 5-7 ms and the rest the sweeps (211 colours, 12 sweeps per step).

Here each step instead:
1. bounds every body by a box (its AABB grown by half the speculative distance on each side) and
   keeps the slots whose two boxes overlap and whose bodies may collide (one cheap elementwise test
   per slot and scene), compacted into each scene's own fixed-capacity candidate list per kind of
   pair (`capacities`);
2. runs the narrow phase on the candidates only;
3. colours each scene's candidates that hold a point, in `jit`: rounds of a parallel greedy matching
   (a pair joins the round's colour when it has the lowest of a fixed pseudo-random priority among
   the uncoloured pairs at each of its moving bodies; three tries per round). A body static in the
   scene may repeat within a colour (its velocity never changes), as in pairs.wall_grouped;
4. hands the contact solver a `DynamicLayout`: the same attributes as pairs.ContactLayout with
   traced arrays, one set per scene (batch last), so the sweeps visit only the few colours of the
   touching pairs and gather each scene's sides with its own indices (math2d.take_rows).
Everything is per scene, so a scene's result does not depend on the batch it is stepped in, and a
batch costs about its size times one scene.
The persistent state is unchanged (one slot per pair): results are gathered from and scattered
back to the slots, so warm starting matches impulses by slot and feature key as before.

Overflow: a candidate list holds at most `capacities` pairs per scene; pairs beyond it, and
touching pairs the colouring could not place in MAX_COLOURS colours, get no contact in that step
(they are dropped whole, so the step stays well defined). `overflow` counts both kinds for a
state, outside the step (tests and diagnostics). Greedy colouring needs at most 2d - 1 colours, d the
most touching pairs of one moving body; the parallel rounds need a few more.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jax2d.collide import Manifold, collide_circles, collide_polygon_circle, collide_polygons
from jax2d.math2d import take_rows
from jax2d.narrow_phase import empty_rows, joint_connected, joint_labels, pair_filter, pair_inputs, step_reach
from jax2d.pairs import CIRCLE_CIRCLE, CIRCLE_POLY, PADDING, POLY_CIRCLE, POLY_POLY, ContactLayout, contact_layout
from jax2d.state import SimParams

# With SolverConfig.broad_phase None, scenes of more than AUTO_BODIES bodies use the broad phase, at any
# batch size: candidates and colourings are per scene, so its cost grows with the batch as the all-pairs
# path's does. Measured on this 2-core machine under load (docs/engine.md; 20-step scans, one device): the
# xl bench scene (80 bodies) took 2.2-2.8 against 3.2-5.9 ms a step at batch 1, 20-31 against 25-48 ms at
# batch 16 and 108-115 against 165-180 ms at batch 64; the l class (16 bodies) is fastest with all pairs.
AUTO_BODIES = 40
# Candidate pairs kept per scene: CANDIDATES_PER_BODY times the bodies a kind of pair involves
# (a box in a pyramid overlaps about 6 others, each pair counted once: 3 per body).
CANDIDATES_PER_BODY = 4
# Colouring rounds; a colour holds up to 2 x candidates / MAX_COLOURS pairs (at least MIN_WIDTH). Only touching
# pairs take a solve position; the rest of the list is solved nowhere. Until issue 35 every candidate row had a
# position and the candidate list was padded to the layout's size (1,280 rows per xl scene for ~125 touching
# pairs), so the constraints of 1,280 rows were prepared in every step; now 641. The width is kept: narrower
# colours would put the touching pairs in more colours, and each colour costs the same few hundred kernels per
# sweep whatever its width (not measured: the machine was too loaded to tell).
MAX_COLOURS = 32
MIN_WIDTH = 8
TRIES_PER_COLOUR = 3  # matching attempts per round (each adds pairs that do not touch the earlier ones)


def uses_broad_phase(broad_phase: bool | None, num_bodies: int) -> bool:
    """Whether scenes of `num_bodies` bodies are stepped with the broad phase (SolverConfig.broad_phase)."""
    if broad_phase is not None:
        return bool(broad_phase)
    return num_bodies > AUTO_BODIES


@dataclasses.dataclass(frozen=True, eq=False)
class Candidates:
    """The step's candidate pairs: L rows, each a slot of the all-pairs layout (or padding)."""

    num_padded: int  # M
    slot: jax.Array  # (L, B) int32 slot index; S (out of range) for padding rows
    slot_a: jax.Array  # (L, B) body of side a (0 for padding)
    slot_b: jax.Array  # (L, B) body of side b (0 for padding)
    slot_kind: jax.Array  # (L, B) pairs.POLY_POLY ... ; PADDING for padding rows
    lists: tuple  # per narrow-phase call: (call, rows, bodies a (rows, B), bodies b, normal sign or None)
    dropped: jax.Array  # (B,) int32 close pairs beyond the capacity, per scene


@dataclasses.dataclass(frozen=True, eq=False)
class DynamicLayout:
    """pairs.ContactLayout's attributes for the contact solver, computed in the step."""

    num_padded: int
    num_colours: int
    per_colour: int
    slot_a: jax.Array  # (L, B), as Candidates
    slot_b: jax.Array
    slot_kind: jax.Array
    solve_slots: jax.Array  # (C * K, B) candidate row at each solve position, per scene
    slot_order: jax.Array  # (L, B) solve position of each candidate row
    solve_sides: jax.Array  # (C, 2K, B)
    write_back: jax.Array  # (C, M, B)
    walls_repeat: bool = True

    @property
    def num_slots(self) -> int:
        return self.num_colours * self.per_colour


def _kind_lists(layout: ContactLayout):
    """Per narrow-phase call: (call, slots, bodies a, bodies b, normal sign or None) as numpy. Polygon-circle
    pairs in either order share one call ("pc", polygon first); circle-first slots flip the normal."""
    k, a, b = layout.by_kind, layout.slot_a, layout.slot_b
    out = []
    pp = k[POLY_POLY]
    if len(pp):
        out.append(("pp", pp, a[pp], b[pp], None))
    pc, cp = k[POLY_CIRCLE], k[CIRCLE_POLY]
    if len(pc) + len(cp):
        out.append(("pc", np.concatenate([pc, cp]), np.concatenate([a[pc], b[cp]]), np.concatenate([b[pc], a[cp]]),
                    np.concatenate([np.ones(len(pc)), -np.ones(len(cp))]).astype(np.float32)))
    cc = k[CIRCLE_CIRCLE]
    if len(cc):
        out.append(("cc", cc, a[cc], b[cc], None))
    return out


def capacities(layout: ContactLayout) -> list[int]:
    """Candidate rows of each narrow-phase call, per scene."""
    caps = []
    for _, slots, a, b, _ in _kind_lists(layout):
        bodies = len(np.unique(np.concatenate([a, b])))
        caps.append(int(min(len(slots), CANDIDATES_PER_BODY * bodies)))
    return caps


def boxes(b, speculative, reach=None) -> jax.Array:
    """(4, M?, *batch) lower x, lower y, upper x, upper y of every body (batch-last bodies), grown by
    half the speculative distance and the body's reach in the step (narrow_phase.step_reach; (N, *batch) or None)
    on each side, so two boxes overlap whenever the narrow phase could find a point (its margin is the
    speculative distance plus both reaches)."""
    pos, ang = b.position, b.angle  # (N, 2, *batch), (N, *batch)
    P = b.vertices.shape[0]
    grow = 0.5 * jnp.asarray(speculative, jnp.float32)
    c, s = jnp.cos(ang[:P]), jnp.sin(ang[:P])
    vx, vy = b.vertices[:, :, 0], b.vertices[:, :, 1]  # (P, V, *batch)
    real = jnp.arange(vx.shape[1]).reshape((1, -1) + (1,) * (vx.ndim - 2)) < b.n_vertices[:, None]
    wx = jnp.where(real, c[:, None] * vx - s[:, None] * vy, 0.0)
    wy = jnp.where(real, s[:, None] * vx + c[:, None] * vy, 0.0)
    px, py = pos[:P, 0], pos[:P, 1]
    big = jnp.float32(1e9)
    poly = jnp.stack([px + jnp.min(jnp.where(real, wx, big), axis=1), py + jnp.min(jnp.where(real, wy, big), axis=1),
                      px + jnp.max(jnp.where(real, wx, -big), axis=1), py + jnp.max(jnp.where(real, wy, -big), axis=1)])
    cx, cy, r = pos[P:, 0], pos[P:, 1], b.radius
    circle = jnp.stack([cx - r, cy - r, cx + r, cy + r])
    box = jnp.concatenate([poly, circle], axis=1)
    if reach is not None:
        grow = grow + reach
    return box + jnp.array([-1.0, -1.0, 1.0, 1.0], jnp.float32).reshape((4, 1) + (1,) * (box.ndim - 2)) * grow


def candidates(layout: ContactLayout, b, speculative, may_collide, extra_rows: int = 0, reach=None) -> Candidates:
    """Each scene's slots whose boxes overlap and whose bodies may collide (bodies batch-last (N, ..., B);
    may_collide (S, B), pair_filter without joints), compacted per kind and scene; then `extra_rows`
    padding rows. Every index array of the result is (L, B): row l of scene s is that scene's own pair.
    reach: as in boxes."""
    box = boxes(b, speculative, reach)
    B = box.shape[2]
    S = layout.num_slots
    lists, slots, sa, sb, kinds = [], [], [], [], []
    dropped = jnp.zeros((B,), jnp.int32)
    compact = jax.vmap(lambda close, cap: jnp.nonzero(close, size=cap, fill_value=0)[0], in_axes=(1, None),
                       out_axes=1)
    for (call, idx, a, c, sign), cap in zip(_kind_lists(layout), capacities(layout), strict=True):
        ba, bb = box[:, a], box[:, c]
        close = (ba[0] <= bb[2]) & (bb[0] <= ba[2]) & (ba[1] <= bb[3]) & (bb[1] <= ba[3]) & may_collide[idx]
        count = jnp.sum(close, axis=0, dtype=jnp.int32)  # (B,)
        dropped = dropped + jnp.maximum(count - cap, 0)
        row = compact(close, cap).astype(jnp.int32)  # (cap, B)
        filled = jnp.arange(cap)[:, None] < count
        ia, ic = jnp.asarray(a, jnp.int32)[row], jnp.asarray(c, jnp.int32)[row]
        lists.append((call, cap, ia, ic, None if sign is None else jnp.asarray(sign)[row]))
        slot = jnp.asarray(idx, jnp.int32)[row]
        kind = jnp.asarray(layout.slot_kind, jnp.int32)[slot]
        slots.append(jnp.where(filled, slot, S))
        kinds.append(jnp.where(filled, kind, PADDING))
        # The solver's sides keep the slot's own order (a, b), so normals point from a to b.
        sa.append(jnp.asarray(layout.slot_a, jnp.int32)[slot])
        sb.append(jnp.asarray(layout.slot_b, jnp.int32)[slot])
    pad = jnp.zeros((extra_rows, B), jnp.int32)
    return Candidates(layout.num_padded, jnp.concatenate(slots + [pad + S]), jnp.concatenate(sa + [pad]),
                      jnp.concatenate(sb + [pad]), jnp.concatenate(kinds + [pad + PADDING]), tuple(lists), dropped)


def rows_for(layout: ContactLayout) -> tuple[int, int, int]:
    """(candidate rows before padding, colours, colour width) of each scene. The candidate list has one padding
    row after the candidates (PAD_ROWS), the row that the solve layout's empty positions point at."""
    rows = max(1, sum(capacities(layout)))
    return (rows,) + solve_size(rows)


def solve_size(rows: int) -> tuple[int, int]:
    """(colours, colour width) of the solve layout for a candidate list of `rows` rows (before padding)."""
    return MAX_COLOURS, max(MIN_WIDTH, -(-2 * rows // MAX_COLOURS))


PAD_ROWS = 1  # padding rows after each scene's candidates: never live


def collide_candidates(cand: Candidates, b, speculative, total: int, reach=None) -> Manifold:
    """Manifolds of the candidate rows (batch-last), padding rows empty; total = rows with padding. A pair's
    margin is the speculative distance plus both bodies' reach (narrow_phase.narrow_phase; reach None: zero)."""
    P = b.vertices.shape[0]
    pos, ang, verts, nv, rad = b.position, b.angle, b.vertices, b.n_vertices, b.radius
    batch, mapped, spec, reach = pair_inputs(b, speculative, reach)

    def margin(i, j):
        return spec + take_rows(reach, i) + take_rows(reach, j)

    parts = []
    for call, _, i, j, sign in cand.lists:  # each scene's own bodies: (rows, B) indices
        t = functools.partial(take_rows, idx=i)
        if call == "pp":
            u = functools.partial(take_rows, idx=j)
            parts.append(mapped(collide_polygons, 8)(
                t(pos), t(ang), t(verts), t(nv), u(pos), u(ang), u(verts), u(nv), margin(i, j)))
        elif call == "pc":
            m = mapped(collide_polygon_circle, 6)(t(pos), t(ang), t(verts), t(nv), take_rows(pos, j),
                                                  take_rows(rad, j - P), margin(i, j))
            parts.append(dataclasses.replace(m, normal=m.normal * sign[:, None]))
        else:
            parts.append(mapped(collide_circles, 4)(t(pos), take_rows(rad, i - P), take_rows(pos, j),
                                                    take_rows(rad, j - P), margin(i, j)))
    n = sum(x[1] for x in cand.lists)
    return jax.tree.map(lambda *xs: jnp.concatenate(xs), *parts, empty_rows(total - n, batch))


class Found(NamedTuple):
    """What the broad and narrow phase of a step give the rest of it (`find`), every array batch-last."""

    cand: Candidates
    manifold: Manifold  # (L, ...) per candidate row
    jointed: jax.Array  # (L, B) rows whose bodies a chain of joints connects
    group: jax.Array  # (M, B) each body's joint group (narrow_phase.joint_labels), for the walls' stages
    contacts: object  # state.Contacts of each row's slot last step (padding rows: no point)


def find(layout: ContactLayout, scene, joints, speculative, reach) -> Found:
    """The step's broad and narrow phase for big scenes: each scene's candidate pairs, their manifolds, which are
    jointed, the bodies' joint groups and their slots' old contacts. scene: the batch-last state; joints: the
    batch-first state.joints (the joint closure runs per scene); reach: (N, B) step_reach."""
    M, S = layout.num_padded, layout.num_slots
    B = scene.bodies.active.shape[-1]
    rows, _, _ = rows_for(layout)
    total = rows + PAD_ROWS
    may_collide = pair_filter(layout, scene.bodies, jnp.zeros((S, B), bool), M)
    cand = candidates(layout, scene.bodies, speculative, may_collide, PAD_ROWS, reach)
    manifold = collide_candidates(cand, scene.bodies, speculative, total, reach)
    # Each body's joint group, once: the rows' "jointed" here and the walls' stages later (Found.group).
    group = jax.vmap(lambda j: joint_labels(j, M))(joints)  # (B, M)
    jointed = jax.lax.cond(
        jnp.any(joints.active),
        lambda: jax.vmap(lambda g, a, b: g[a] == g[b])(group, cand.slot_a.T, cand.slot_b.T),
        lambda: jnp.zeros((B, total), bool))
    # Each scene's old contacts of its candidates (padding rows: slot S, out of range, filled with 0).
    contacts = jax.tree.map(lambda x: take_rows(x, cand.slot, fill=0), scene.contacts)
    contacts = dataclasses.replace(contacts, key=jnp.where(cand.slot[:, None] < S, contacts.key, -1))
    return Found(cand, manifold, jnp.moveaxis(jointed, 0, -1), group.T, contacts)


def to_slots(cand: Candidates, num_slots: int, x, fill):
    """(B, L, ...) per candidate row, batch-first -> (B, S, ...) per slot, by each scene's slots; padding rows
    and slots without a candidate get `fill`."""
    return jax.vmap(lambda x, slot: jnp.full((num_slots,) + x.shape[1:], fill, x.dtype).at[slot].set(x, mode="drop"))(
        x, cand.slot.T)


@functools.cache
def _priority(rows: int) -> np.ndarray:
    """A fixed pseudo-random priority per candidate row (a permutation): the colouring's tie-breaker.
    Random rather than the row order, so chains of pairs resolve in a few rounds, not one per pair."""
    return np.random.default_rng(28).permutation(rows).astype(np.int32)


def colour(cand: Candidates, live, shareable, num_padded: int) -> tuple[DynamicLayout, jax.Array]:
    """Colour each scene's live candidate rows (L, B) (a point in the scene); shareable (M, B): bodies static in
    the scene, which may repeat within a colour. Returns the layout (every index array per scene, batch last)
    and the rows it placed (L, B) (live ones beyond MAX_COLOURS rounds are not)."""
    # The rounds visit the candidate rows only: the padding rows after them (extra_rows) are never live.
    n = sum(x[1] for x in cand.lists)
    colours, width = solve_size(max(1, n))
    col, pos = _rounds(cand.slot_a[:n], cand.slot_b[:n], live[:n], shareable, num_padded, colours, width,
                       _priority(colours * width)[:n])
    fill = jnp.full((live.shape[0] - n,) + col.shape[1:], -1, jnp.int32)
    col, pos = jnp.concatenate([col, fill]), jnp.concatenate([pos, fill])
    one = functools.partial(_positions, num_padded=num_padded, colours=colours, width=width)
    solve, order, sides, back = jax.vmap(one, in_axes=1, out_axes=-1)(cand.slot_a, cand.slot_b, col, pos)
    layout = DynamicLayout(num_padded, colours, width, cand.slot_a, cand.slot_b, cand.slot_kind, solve, order, sides,
                           back)
    return layout, col >= 0


def _rounds(a, b, live, shareable, M: int, colours: int, width: int, priority: np.ndarray):
    """The colouring rounds for every scene at once: (L, B) colour and solve position of each row (-1: none).

    Batch-last with flat indices (body * B + scene) into (M * B,) arrays, so each scatter and gather is a
    plain one-dimensional one: the same rounds under vmap (a batched scatter per try) took 16x longer at
    batch 16 than at batch 1. priority: (L,) each row's distinct tie-breaker (the padded list's _priority
    cut to the candidate rows, so a scene is coloured as when the rounds visited the padding rows too).
    """
    L, B = live.shape
    scene = jnp.arange(B, dtype=jnp.int32)
    fa, fb = (a * B + scene).reshape(-1), (b * B + scene).reshape(-1)
    # Rows that are not live scatter nowhere (an index past the end, dropped): most rows in a step.
    sa, sb = jnp.where(live.reshape(-1), fa, M * B), jnp.where(live.reshape(-1), fb, M * B)
    share = shareable.reshape(-1)
    share_a, share_b = share[fa].reshape(L, B), share[fb].reshape(L, B)
    prio = jnp.asarray(priority)[:, None]
    none = jnp.int32(np.iinfo(np.int32).max)  # above every priority

    def one_round(carry):
        r, col, pos = carry
        free = live & (col < 0)
        chosen = jnp.zeros((L, B), bool)
        blocked = jnp.zeros((L, B), bool)
        for _ in range(TRIES_PER_COLOUR):
            try_ = free & ~blocked & ~chosen
            p = jnp.where(try_, prio, none)
            best = jnp.full((M * B,), none).at[sa].min(p.reshape(-1), mode="drop").at[sb].min(p.reshape(-1),
                                                                                               mode="drop")
            win = try_ & ((best[fa].reshape(L, B) == p) | share_a) & ((best[fb].reshape(L, B) == p) | share_b)
            chosen = chosen | win
            c = chosen.reshape(-1)
            used = jnp.zeros((M * B,), bool).at[sa].max(c, mode="drop").at[sb].max(c, mode="drop") & ~share
            blocked = (used[fa] | used[fb]).reshape(L, B)
        rank = jnp.cumsum(chosen, axis=0, dtype=jnp.int32) - 1
        take = chosen & (rank < width)
        return r + 1, jnp.where(take, r, col), jnp.where(take, r * width + rank, pos)

    def more(carry):
        r, col, _ = carry
        return (r < colours) & jnp.any(live & (col < 0))

    start = (jnp.int32(0), jnp.full((L, B), -1, jnp.int32), jnp.full((L, B), -1, jnp.int32))
    _, col, pos = jax.lax.while_loop(more, one_round, start)
    return col, pos


def _positions(a, b, col, pos, *, num_padded: int, colours: int, width: int):
    """One scene's layout arrays from its colouring ((L,) sides, colours and positions): (solve slots, slot
    order, solve sides, write back).

    Placed rows sit where the colouring put them; the other positions hold the last row, a padding row (no
    point: nothing to solve), and the rows left without a position have slot order n, out of range (their
    impulses unpack as 0: sweeps.unpack_rows)."""
    L, M = col.shape[0], num_padded
    placed = col >= 0
    n = colours * width
    at_pos = jnp.where(placed, pos, n)
    solve = jnp.full((n,), L - 1, jnp.int32).at[at_pos].set(jnp.arange(L, dtype=jnp.int32), mode="drop")
    order = at_pos.astype(jnp.int32)
    sides = jnp.concatenate([a[solve].reshape(colours, width), b[solve].reshape(colours, width)], axis=1)
    k = pos - col * width
    c_idx = jnp.where(placed, col, colours)
    back = jnp.tile(jnp.arange(M, dtype=jnp.int32), (colours, 1))
    back = back.at[c_idx, a].set(M + k, mode="drop").at[c_idx, b].set(M + width + k, mode="drop")
    return solve, order, sides, back


class Overflow(NamedTuple):
    candidates: int  # close pairs beyond the candidate capacity
    colours: int  # touching candidate pairs that MAX_COLOURS colours could not place


def overflow(state, params=None, num_static: int = 0) -> Overflow:
    """The pairs of one scene that a broad-phase step from `state` would leave without contacts: close pairs
    (overlapping boxes, bodies that may collide) beyond the candidate capacity, and touching pairs the
    colouring could not place. For tests and diagnostics, outside jit (the step keeps no counter)."""
    params = SimParams() if params is None else params
    layout = contact_layout(state.num_polygons, state.num_circles, num_static)
    M = layout.num_padded
    scene = jax.tree.map(lambda x: jnp.asarray(x)[..., None], state)
    may = pair_filter(layout, scene.bodies, jnp.zeros((layout.num_slots, 1), bool), M)
    spec = jnp.full((1,), params.speculative_distance, jnp.float32)
    rows, colours, width = rows_for(layout)
    reach = step_reach(scene, params.dt)
    cand = candidates(layout, scene.bodies, spec, may, PAD_ROWS, reach)
    manifold = collide_candidates(cand, scene.bodies, spec, rows + PAD_ROWS, reach)
    jointed = joint_connected(state.joints, M)[cand.slot_a, cand.slot_b]  # (L, 1)
    live = jnp.any(manifold.valid, axis=1) & (cand.slot_kind != PADDING) & ~jointed
    b = state.bodies
    moving = jnp.zeros((M, 1), bool).at[:b.active.shape[0], 0].set(b.active & (b.inv_mass > 0))
    _, placed = colour(cand, live, ~moving, M)
    return Overflow(int(jnp.sum(cand.dropped)), int(jnp.sum(live & ~placed)))
