"""Packed colour rows and the colour sweep: the machinery every contact pass runs on.

Slots are solved colour by colour (pairs.py, broad_phase.py): within a colour no body appears twice (bar
static ones), so a colour is one vectorised update and a sweep over the colours is an exact Gauss-Seidel
pass. The passes that use it: the contact solver's warm start, solve and relax (contact_solver.py), the
restitution stage (restitution.py) and the static walls' push-out (static_walls.py). Each supplies a
`solve_colour` function; `sweep` runs it on the live colours of a `Schedule`.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jax2d.math2d import Vel, at, gather_scene_rows, scene_rows, set_at, take_rows
from jax2d.pairs import ContactLayout

# Packed layout. Inside the sweeps every per-slot quantity is one row of a colour-major
# (C, F, K) array: the scan slices one (F, K) block per colour, each field a contiguous row
# of the colour's K slots. Constraint data is packed once per step; impulses stay packed
# through all substeps.
#
# A colour's velocities are the (3, 2K) rows the sweep gathers, viewed as six rows of K (VEL_ROWS).
# An impulse p along a point's normal or tangent changes them by p times six constant rows, its
# push rows (the inverse masses times the constraint's Jacobian), which prepare packs once per
# step: a velocity update is then one elementwise kernel over contiguous rows.
VEL_ROWS = ("xa", "xb", "ya", "yb", "wa", "wb")  # x of side a, x of side b, y of a, y of b, w of a, w of b
PUSH_ROWS = {(kind, k): tuple(f"{kind}{k}_{v}" for v in VEL_ROWS) for kind in ("normal", "tangent") for k in range(2)}
CONST_ROWS = ("nx", "ny", "friction", "restitution", "gn",
              "rax0", "rax1", "ray0", "ray1", "rbx0", "rbx1", "rby0", "rby1",
              "nmass0", "nmass1", "tmass0", "tmass1", "rel0", "rel1", "boost0", "boost1",
              "soft0", "soft1", "stiff0", "stiff1") + sum(PUSH_ROWS.values(), ())
IMPULSE_ROWS = ("n0", "n1", "t0", "t1", "max0", "max1")
ROW = {name: i for i, name in enumerate(CONST_ROWS)}
NORMAL, TANGENT, MAX = 0, 2, 4  # first impulse row of the normal, tangent and largest normal impulses


def pack_rows(layout: ContactLayout, rows) -> jax.Array:
    """A list of (S, *batch) arrays, slot order -> (C, F, K, *batch), solve order.

    With one solve order for every scene (a numpy permutation), the rows are placed by one gather with
    constant indices, field and slot together, straight into the (C, F, K) layout. Gathering the slots and
    then swapping the field and colour axes made XLA write the packed constraints twice (a layout copy of
    all 49 rows): env s at batch 256 ran 16-19 % faster without it, bitwise the same.
    """
    C, K = layout.num_colours, layout.per_colour
    stacked = jnp.stack(rows).astype(jnp.float32)
    slots = layout.solve_slots if layout.walls_repeat else np.arange(C * K)
    if isinstance(slots, np.ndarray) and slots.ndim == 1:
        return stacked[np.arange(len(rows)).reshape(1, -1, 1), slots.reshape(C, 1, K)]
    stacked = take_rows(stacked, slots, axis=1)  # each scene its own order (broad_phase)
    return jnp.swapaxes(stacked.reshape((len(rows), C, K) + stacked.shape[2:]), 0, 1)


def unpack_rows(layout: ContactLayout, packed) -> jax.Array:
    """(C, F, K, *batch), solve order -> (F, S, *batch), slot order. A per-scene slot order ((S, B): the broad
    phase's layouts) may point past the end, for rows that were not solved: they unpack as 0."""
    C, F, K = packed.shape[:3]
    rows = jnp.swapaxes(packed, 0, 1).reshape((F, C * K) + packed.shape[3:])
    if not layout.walls_repeat:
        return rows
    return take_rows(rows, layout.slot_order, axis=1, fill=0.0 if jnp.ndim(layout.slot_order) == 2 else None)


def relative_velocity(vax, vay, wa, vbx, vby, wb, rax, ray, rbx, rby):
    """Velocity of the contact point on b relative to the one on a."""
    return (vbx - wb * rby) - (vax - wa * ray), (vby + wb * rbx) - (vay + wa * rax)


class Rows:
    """Colour c's rows of a packed (C, F, K, *batch) array, read row by row where they are used.

    Each read is a dynamic slice that XLA fuses into the kernel reading it; slicing the colour's
    whole (F, K) block first made the solver copy it in every colour of every sweep, because
    the conditionals that read a few of its rows take the block as an operand.
    """

    def __init__(self, packed, c):
        self.packed, self.c = packed, c

    def __getitem__(self, i):
        return at(self.packed[:, i], self.c)


class Block(Rows):
    """Named access to colour c's constant rows (CONST_ROWS)."""

    def __getattr__(self, name):
        if name.startswith("__"):  # copy and pickle probe for these
            raise AttributeError(name)
        return self[ROW[name]]

    def point(self, name, k: int):
        """Row of point k."""
        return self[ROW[f"{name}{k}"]]

    def push(self, kind: str, k: int):
        """(6, K, *batch) the push rows of point k's normal or tangent."""
        i = ROW[PUSH_ROWS[(kind, k)][0]]
        return self[i:i + len(VEL_ROWS)]


class Schedule(NamedTuple):
    """Which colours a step's sweeps visit: the first `count` entries of `order`, in colour order.

    A fixed schedule (jax2d/control.py) visits every colour: count is the colour count as a Python int (a loop
    XLA knows the trip count of) and points is None (both points of every colour are solved)."""

    order: jax.Array  # (C,) int32: the live colours first (ascending), then the others
    count: jax.Array | int  # () int32: how many colours are live; an int in a fixed schedule
    points: jax.Array | None  # (C,) int32: 2 if a slot of the colour has a second point in some scene, else 1

    @property
    def fixed(self) -> bool:
        return isinstance(self.count, int)


def schedule(const, fixed: bool = False, rows: str = "nmass") -> Schedule:
    """The colours with a point in any scene of the batch (packed const, batch-last); with `fixed`, every
    colour and both points (jax2d/control.py). rows: the per-point constant rows that are positive where a
    point counts ("nmass": every point; "stiff": the points stiffened by their load, contact_solver.load_softness).

    A colour with no point has zero masses and zero impulses, so solving it changes nothing
    and the sweeps skip it. Most colours are empty in a real level (the reference levels
    touch 3 of 7, 9 and 15 on average), so this makes a step at a small batch much cheaper;
    a batch of very different scenes skips only the colours empty in all of them.

    Likewise a colour's second point is skipped where no slot of it has one in any scene
    (contacts with a circle have one point): solving an absent point changes nothing.
    """
    if fixed:
        return Schedule(jnp.arange(const.shape[0], dtype=jnp.int32), const.shape[0], None)
    i = ROW[f"{rows}0"]
    masses = const[:, i:i + 2]
    live = jnp.any(masses > 0.0, axis=tuple(range(1, masses.ndim)))
    order = jnp.argsort(~live, stable=True).astype(jnp.int32)
    second = jnp.any(masses[:, 1] > 0.0, axis=tuple(range(1, masses.ndim - 1)))
    return Schedule(order, jnp.sum(live, dtype=jnp.int32), 1 + second.astype(jnp.int32))


class Chain(NamedTuple):
    """A sweep over one schedule's colours followed by `repeats` sweeps over another's.

    The contact solve and relax run a pass over every live colour and then extra passes over the colours with a
    stiffened point (step.py). As a loop per pass those were three loops of no trips per substep in the many steps
    that have no stiffened point, each copying the packed impulses into its carry. `sweep` runs a chain as two
    loops: the first pass, then all the repeats, each visit in the branch of its pass (docs/engine.md, "One
    branch per pass"). Per visit: its colour, its pass (0 the first schedule's, r its r-th repeat of the second)
    and its points (Schedule.points of its colour; None in a fixed chain)."""

    colour: jax.Array  # (V,) int32
    pass_of: jax.Array  # (V,) int32
    points: jax.Array | None  # (V,) int32
    count: jax.Array | int  # visits; an int in a fixed chain (jax2d/control.py)
    first: jax.Array | int  # the first pass's visits (they come first)
    passes: int  # 1 + repeats

    @property
    def fixed(self) -> bool:
        return isinstance(self.count, int)


def chain(first: Schedule, then: Schedule, repeats: int) -> Chain:
    """One sweep over `first`'s colours, then `repeats` over `then`'s (both of the same packed rows)."""
    C = first.order.shape[0]
    passes = 1 + repeats
    if first.fixed:
        return Chain(jnp.asarray(np.tile(np.arange(C, dtype=np.int32), passes)),
                     jnp.asarray(np.repeat(np.arange(passes, dtype=np.int32), C)), None, C * passes, C, passes)
    visit = jnp.arange(C * passes, dtype=jnp.int32)
    later = visit - first.count  # the visit's index among the repeats' visits
    per_repeat = jnp.maximum(then.count, 1)
    in_first = later < 0
    colour = jnp.where(in_first, first.order[jnp.minimum(visit, C - 1)], then.order[jnp.maximum(later, 0) % per_repeat])
    pass_of = jnp.where(in_first, 0, 1 + jnp.maximum(later, 0) // per_repeat)
    points = jnp.where(in_first, first.points[colour], then.points[colour])
    return Chain(colour, pass_of.astype(jnp.int32), points, first.count + repeats * then.count, first.count,
                 passes)


def sweep(layout: ContactLayout, vel: Vel, solve_colour, const, impulses, plan: Schedule | Chain, *inputs):
    """Run `solve_colour(vels, lam, points, const_block, *input_rows) -> (vels, lam)` on every live
    colour in order. vels: the colour's (6, K, *batch) VEL_ROWS; lam: its (6, K, *batch) impulse
    rows; points: how many of the two points any slot of the colour has (traced; a Python int in a small colour,
    below; None in a fixed schedule: both); const_block and input_rows: the colour's rows of const and of each
    packed (C, F, K, *batch) input. A solve_colour that changes no impulse returns lam None.

    A loop over the schedule's live colours: each iteration gathers the velocities of the K bodies
    of side a and the K of side b as one (3, 2K, *batch) array, solves, and writes them back by a
    gather (layout.write_back). One array rather than six: each gather and velocity update is then
    one kernel, and a step at a small batch is a long chain of such small kernels. Skipped colours
    keep their impulses, which is what solving them would give. With a Chain plan, solve_colour gets the
    visit's pass as a last argument (a Python int: 0 for the first schedule's sweep, r for the r-th repeat).
    Returns the velocities and the packed (C, 6, K, *batch) impulses.

    Small colours (K x batch at most FUSED_POINTS): each visit is the branch of a conditional on its point count,
    solve_colour getting 1 or 2 as a Python int. XLA's CPU runtime runs a sequence of at most 8 thunks (kernels,
    copies, loops, conditionals) one after the other on the calling thread, and a longer one as a graph, handing
    independent thunks to its thread pool, which costs a heap-allocated state per run and wakes the other core's
    worker (engine l at batch 1: 3.5 context switches a step). A visit was 12-16 thunks; as a conditional, the
    loop body is at most 8 and so is each branch (engine l at batch 1: +26-51 %, s at 16 +13 %, m at 64 +11 %).
    """
    K = layout.per_colour
    sides, write_back = jnp.asarray(layout.solve_sides), jnp.asarray(layout.write_back)
    stacked = jnp.stack(vel)  # (3, M, *batch)
    batch = stacked.shape[2:]
    if sides.ndim == 3:  # (C, 2K, B): each scene its own sides (broad_phase); flat indices into (3, M * B)
        sides, write_back = scene_rows(sides, batch[0]), scene_rows(write_back, batch[0])
        gather = gather_scene_rows
    else:
        def gather(v, idx):
            return v[:, idx]

    chained = isinstance(plan, Chain)

    def colour(v, lam, c, i, visit_pass=()):
        def solved(points):
            vels = gather(v, at(sides, c)).reshape((6, K) + batch)
            vels, new = solve_colour(vels, lam, points, Block(const, c), *(Rows(x, c) for x in inputs), *visit_pass)
            return gather(jnp.concatenate([v, vels.reshape((3, 2 * K) + batch)], axis=1), at(write_back, c)), new

        points = None if plan.points is None else at(plan.points, i if chained else c)
        if points is None or K * math.prod(batch) > FUSED_POINTS:
            return solved(points)
        return jax.lax.cond(points > 1, functools.partial(solved, 2), functools.partial(solved, 1))

    def visited(i):  # the i-th colour the sweep visits
        if chained:
            return at(plan.colour, i)
        return i if plan.fixed else at(plan.order, i)

    first_pass = (0,) if chained else ()
    probe = jax.eval_shape(lambda: solve_colour(jnp.zeros((6, K) + batch), impulses[0], None, Block(const, 0),
                                                *(Rows(x, 0) for x in inputs), *first_pass)[1])
    updates = probe is not None  # else the loop carries the velocities only

    def visit(p, i, c, v, out):
        """Visit i, of colour c, in pass p (None: a plain schedule's) -> (velocities, the colour's impulses).
        It reads the input's impulses, not the carry's: reading a slice of the array the loop updates in place
        made XLA copy all of it in every iteration. A chain's first pass visits each colour once, before any
        repeat, so it may too; the repeats visit colours again and read the carry."""
        return colour(v, at(out if p else impulses, c), c, i, () if p is None else (p,))

    def body(p):
        """The loop body of pass p (None: a plain schedule's); "repeats": a chain's repeats, each visit in the
        branch of its pass (a conditional). Each pass's colour update compiles with its pass a constant: with the
        pass traced, every row a point reads was a dynamic slice, and a visit at l, batch 1, ran 68 kernels and
        copies against 48. The first pass has a loop of its own, without the conditional: in one loop with it,
        env l at batch 1 ran 20-25 % slower (docs/engine.md, "One branch per pass")."""
        def run(i, carry):
            v, out = carry if updates else (carry, impulses)
            c = visited(i)
            if p == "repeats":
                branches = [functools.partial(visit, q, i, c) for q in range(1, plan.passes)]
                v, lam = jax.lax.switch(at(plan.pass_of, i) - 1, branches, v, out)
            else:
                v, lam = visit(p, i, c, v, out)
            return (v, set_at(out, c, lam)) if updates else v
        return run

    carry = (stacked, impulses) if updates else stacked
    if not chained:
        carry = jax.lax.fori_loop(0, plan.count, body(None), carry)
    elif plan.fixed:  # a loop per pass: no conditional (jax2d/control.py), and each loop's count is known
        per_pass = plan.count // plan.passes
        for p in range(plan.passes):
            carry = jax.lax.fori_loop(p * per_pass, (p + 1) * per_pass, body(p), carry)
    else:
        carry = jax.lax.fori_loop(0, plan.first, body(0), carry)
        carry = jax.lax.fori_loop(plan.first, plan.count, body(1 if plan.passes == 2 else "repeats"), carry)
    v, impulses = carry if updates else (carry, impulses)
    return Vel(v[0], v[1], v[2]), impulses


def colour_sides(vels) -> tuple[Vel, Vel]:
    """A colour's VEL_ROWS as the velocities of side a and of side b."""
    return Vel(vels[0], vels[2], vels[4]), Vel(vels[1], vels[3], vels[5])


def with_rows(lam, rows) -> jax.Array:
    """lam (6, K, *batch) impulse rows with the rows in `rows` ((row, value) pairs) replaced: an elementwise
    select, so that the update stays one kernel (a stack of rows compiled to one per row)."""
    index = jnp.arange(lam.shape[0]).reshape((-1,) + (1,) * (lam.ndim - 1))
    for row, value in rows:
        lam = jnp.where(index == row, value[None], lam)
    return lam


# Where a colour's row holds at most this many numbers (K slots x batch on one device), `sweep` runs each visit as
# the branch of its point count (1 or 2) and for_points updates the points without conditionals (see sweep).
# Measured with the earlier form of the small path (each point's push fused into its conditional), against 256,
# in one process (kinetix.bench.ab, 2 Dec 2026; s, m and l have K = 4, 5 and 8, and a batch of 256 is 128 a
# device): env m 256 +23 %, env s 256 +9 %, engine m 256 +6 %, engine s 256 +4 %. At 1,024 (l at 128 a device, s
# at a chunk of 256) it lost: engine l 256 -6 %, env s 2048 -1 % (env l 256 +3 %).
FUSED_POINTS = 768


class ImpulseRow(NamedTuple):
    """One impulse row of a colour's points for `for_points`: accumulated(k, vels, lam) -> point k's new
    accumulated impulse of row `row + k`; push(k, vels, lam, new) -> the velocities and impulses with it applied."""

    row: int
    accumulated: object
    push: object


def for_points(points, impulse_rows: tuple[ImpulseRow, ...], vels, lam, reverse: bool = False):
    """Solve the impulse rows of the points k < `points` of a colour, each row point by point (the second first
    with `reverse`), the rows in turn. An absent point keeps its impulse.

    points, as `sweep` passes it:
    - a Python int (a small colour, the visit being the branch of its point count): each point's update is one
      kernel, the velocities and impulses travelling from point to point as one (12, K, *batch) array whose 12 rows
      each compute the point's impulse again; at that size that costs less than the kernels a stored impulse needs;
    - traced (a large colour): each point's new impulse is the branch of a conditional (k < points), so it is
      computed once and stored: XLA's CPU fusion copies a chain of elementwise operations into each of its
      consumers, which would recompute it for every row it changes. Point 0's condition always holds for a live
      colour; XLA cannot know that, so it stays a conditional too. A point's update is then three kernels (the
      impulse, the velocities, the impulses); a point loop over separate arrays took about 18;
    - None (a fixed schedule, jax2d/control.py): every point, without conditionals.
    All three give the same numbers.
    """
    order = (1, 0) if reverse else (0, 1)
    steps = [(r, k) for r in impulse_rows for k in order]
    if points is None:
        for r, k in steps:
            vels, lam = r.push(k, vels, lam, r.accumulated(k, vels, lam))
        return vels, lam
    if isinstance(points, int):
        n = vels.shape[0]
        both = jnp.concatenate([vels, lam])
        for r, k in steps:
            if k < points:
                vels, lam = both[:n], both[n:]
                both = jnp.concatenate(r.push(k, vels, lam, r.accumulated(k, vels, lam)))
        return both[:n], both[n:]
    for r, k in steps:
        new = jax.lax.cond(points > k, functools.partial(r.accumulated, k), lambda v, lam, i=r.row + k: lam[i],
                           vels, lam)
        vels, lam = r.push(k, vels, lam, new)
    return vels, lam


def apply_impulse(c: Block, kind: str, row: int, k: int, vels, lam, new, track_max: bool = False):
    """Apply point k's new accumulated impulse `new` of impulse row `row + k` (its normal or tangent, `kind`):
    the velocities change by the push rows times the difference, the row takes `new`, and with
    `track_max` the point's largest normal impulse so far is kept (restitution reads it)."""
    impulse = new - lam[row + k]
    rows = [(row + k, new)]
    if track_max:
        rows.append((MAX + k, jnp.maximum(lam[MAX + k], impulse)))
    return vels + c.push(kind, k) * impulse[None], with_rows(lam, rows)


def velocity_along(c: Block, k: int, vels, dx, dy):
    """Relative velocity at point k along (dx, dy)."""
    va, vb = colour_sides(vels)
    rax, ray, rbx, rby = c.point("rax", k), c.point("ray", k), c.point("rbx", k), c.point("rby", k)
    dvx, dvy = relative_velocity(va.x, va.y, va.w, vb.x, vb.y, vb.w, rax, ray, rbx, rby)
    return dvx * dx + dvy * dy
