"""The sweeps' schedules: which contact colours and joint slots a step visits."""

import jax.numpy as jnp
import numpy as np
import pytest

from jax2d import joint_solver, sweeps
from jax2d.sweeps import CONST_ROWS


def test_contact_schedule_lists_colours_with_a_point_in_any_scene_in_order():
    C, K, B = 6, 3, 4
    const = np.zeros((C, len(CONST_ROWS), K, B), np.float32)
    const[5, CONST_ROWS.index("nmass1"), 2, 3] = 0.5  # colour 5: point 1 of one slot, in the last scene only
    const[2, CONST_ROWS.index("nmass0"), 0, 0] = 1.0
    const[4, CONST_ROWS.index("tmass0"), 0, 0] = 1.0  # a tangent mass alone is not a point
    plan = sweeps.schedule(jnp.asarray(const))
    assert int(plan.count) == 2
    assert np.asarray(plan.order)[:2].tolist() == [2, 5]
    assert sorted(np.asarray(plan.order).tolist()) == list(range(C))


def test_joint_schedule_lists_slots_active_in_any_scene_in_order():
    J, B = 5, 3
    zeros = jnp.zeros((J, B))
    revolute = zeros.at[3, 1].set(1.0)
    weld = zeros.at[0, 2].set(1.0)
    jc = joint_solver.JointConstraints(*([zeros] * len(joint_solver.JointConstraints._fields)))
    jc = jc._replace(revolute=revolute, weld=weld)
    plan = joint_solver.schedule(jc)
    assert int(plan.count) == 2
    assert np.asarray(plan.order)[:2].tolist() == [0, 3]


def _const_with(points: dict, stiff: dict, C: int, K: int, B: int) -> jnp.ndarray:
    """Packed constant rows with a normal mass at each (colour, point, slot, scene) of `points` and a stiffness row
    at each of `stiff`."""
    const = np.zeros((C, len(CONST_ROWS), K, B), np.float32)
    for rows, name in ((points, "nmass"), (stiff, "stiff")):
        for c, k, slot, scene in rows:
            const[c, CONST_ROWS.index(f"{name}{k}"), slot, scene] = 1.0
    return jnp.asarray(const)


def test_chain_visits_the_first_schedules_colours_then_the_seconds_again_and_again():
    C, K, B = 6, 3, 2
    const = _const_with(points=[(1, 0, 0, 0), (3, 1, 2, 1), (4, 0, 1, 0)], stiff=[(4, 0, 1, 0), (1, 0, 0, 0)],
                        C=C, K=K, B=B)
    colours, stiff = sweeps.schedule(const), sweeps.schedule(const, rows="stiff")
    plan = sweeps.chain(colours, stiff, 2)
    n = int(plan.count)
    assert n == 3 + 2 * 2
    assert np.asarray(plan.colour)[:n].tolist() == [1, 3, 4, 1, 4, 1, 4]
    assert np.asarray(plan.pass_of)[:n].tolist() == [0, 0, 0, 1, 1, 2, 2]
    assert np.asarray(plan.points)[:n].tolist() == [1, 2, 1, 1, 1, 1, 1]  # colour 3's point 1 only in pass 0

    fixed = sweeps.chain(sweeps.schedule(const, fixed=True), sweeps.schedule(const, fixed=True, rows="stiff"), 1)
    assert fixed.count == 2 * C and fixed.points is None
    assert np.asarray(fixed.colour).tolist() == list(range(C)) * 2
    assert np.asarray(fixed.pass_of).tolist() == [0] * C + [1] * C


def test_chain_with_no_second_colour_visits_the_first_schedule_only():
    const = _const_with(points=[(2, 0, 0, 0)], stiff=[], C=4, K=2, B=1)
    plan = sweeps.chain(sweeps.schedule(const), sweeps.schedule(const, rows="stiff"), 3)
    assert int(plan.count) == 1
    assert int(plan.colour[0]) == 2 and int(plan.pass_of[0]) == 0


@pytest.mark.parametrize("repeats", [1, 2])
@pytest.mark.parametrize("fixed", [False, True])
def test_a_chained_sweep_equals_its_sweeps_one_after_the_other(repeats, fixed):
    """A colour visited again in a later pass starts from the impulses its earlier visit left (the sweep reads its
    carry), and each visit is told its pass, as a constant."""
    from jax2d.math2d import Vel
    from jax2d.pairs import contact_layout

    layout = contact_layout(num_polygons=4, num_circles=2)
    C, K, M, B = layout.num_colours, layout.per_colour, layout.num_padded, 3
    rng = np.random.default_rng(0)
    const = np.zeros((C, len(CONST_ROWS), K, B), np.float32)
    const[:, CONST_ROWS.index("nmass0")] = rng.random((C, K, B)) < 0.5
    const[:, CONST_ROWS.index("stiff0")] = (rng.random((C, K, B)) < 0.3) * const[:, CONST_ROWS.index("nmass0")]
    const = jnp.asarray(const)
    impulses = jnp.asarray(rng.random((C, 6, K, B), np.float32))
    vel = Vel(*(jnp.asarray(rng.random((M, B), np.float32)) for _ in range(3)))

    def update(vels, lam, pass_of):  # order-dependent: a stale read of lam or vels changes the result
        return vels * 0.5 + lam[:1].sum() * 0.01 + pass_of, lam * 1.5 + vels[:1].mean() + pass_of

    def chained_colour(vels, lam, points, c, pass_of):
        assert isinstance(pass_of, int)  # each pass compiles on its own (sweeps.sweep)
        return update(vels, lam, pass_of)

    def colour_in(pass_of):
        return lambda vels, lam, points, c: update(vels, lam, pass_of)

    colours, stiff = sweeps.schedule(const, fixed), sweeps.schedule(const, fixed, rows="stiff")
    assert fixed or int(colours.count) > int(stiff.count) > 0
    got_vel, got = sweeps.sweep(layout, vel, chained_colour, const, impulses, sweeps.chain(colours, stiff, repeats))
    want_vel, want = sweeps.sweep(layout, vel, colour_in(0), const, impulses, colours)
    for p in range(1, repeats + 1):
        want_vel, want = sweeps.sweep(layout, want_vel, colour_in(p), const, want, stiff)
    np.testing.assert_array_equal(np.asarray(got), np.asarray(want))
    for g, w in zip(got_vel, want_vel, strict=True):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


@pytest.mark.parametrize("form", ["int", "traced"])
@pytest.mark.parametrize("points", [1, 2])
@pytest.mark.parametrize("reverse", [False, True])
def test_for_points_solves_each_row_point_by_point_in_order(form, points, reverse):
    """Both forms of sweeps.for_points (points a Python int, as a small colour's visit passes it; traced, as a large
    one's) solve the rows in turn, each point after the other, and leave an absent point (k >= points) alone."""
    import functools

    import jax2d

    K, B = 3, 2
    rng = np.random.default_rng(1)
    vels = jnp.asarray(rng.random((6, K, B), np.float32))
    lam = jnp.asarray(rng.random((6, K, B), np.float32))

    def accumulated(row, k, vels, lam):  # reads what the earlier points and rows left
        return lam[row + k] * 0.5 + vels[2 * k].sum(axis=0) * 0.25 + vels[5] * 0.125

    def push(row, k, vels, lam, new):
        delta = new - lam[row + k]
        return vels + delta[None] * (0.5 + k), lam.at[row + k].set(new).at[4].add(delta)

    rows = tuple(sweeps.ImpulseRow(row, functools.partial(accumulated, row), functools.partial(push, row))
                 for row in (0, 2))
    if form == "int":
        got = jax2d.jit(lambda v, lam: sweeps.for_points(points, rows, v, lam, reverse))(vels, lam)
    else:
        got = jax2d.jit(lambda v, lam, n: sweeps.for_points(n, rows, v, lam, reverse))(vels, lam, jnp.int32(points))

    want_v, want_lam = vels, lam
    for r in rows:
        for k in ((1, 0) if reverse else (0, 1)):
            if k < points:
                want_v, want_lam = r.push(k, want_v, want_lam, r.accumulated(k, want_v, want_lam))
    for g, w in zip(got, (want_v, want_lam), strict=True):
        np.testing.assert_allclose(np.asarray(g), np.asarray(w), rtol=1e-6, atol=1e-6)
    assert not np.allclose(np.asarray(got[1]), np.asarray(lam))  # the rows did change


def test_a_sweep_gives_the_same_with_small_colours_branched_by_point_count(monkeypatch):
    """sweep's small-colour form (each visit the branch of its point count, sweeps.FUSED_POINTS) equals the
    large-colour form (a conditional per point) on colours of one and of two points."""
    import functools

    import jax2d
    from jax2d.math2d import Vel
    from jax2d.pairs import contact_layout

    layout = contact_layout(num_polygons=4, num_circles=2)
    C, K, M, B = layout.num_colours, layout.per_colour, layout.num_padded, 2
    rng = np.random.default_rng(3)
    const = np.zeros((C, len(CONST_ROWS), K, B), np.float32)
    const[:, CONST_ROWS.index("nmass0")] = rng.random((C, K, B)) < 0.6
    const[:, CONST_ROWS.index("nmass1")] = (rng.random((C, K, B)) < 0.3) * const[:, CONST_ROWS.index("nmass0")]
    const = jnp.asarray(const)
    impulses = jnp.asarray(rng.random((C, 6, K, B), np.float32))
    vel = Vel(*(jnp.asarray(rng.random((M, B), np.float32)) for _ in range(3)))
    plan = sweeps.schedule(const)
    counts = np.asarray(plan.points)[np.asarray(plan.order)[:int(plan.count)]]
    assert set(counts.tolist()) == {1, 2}  # both kinds of colour are visited

    def accumulated(row, k, vels, lam):
        return lam[row + k] * 0.5 + vels[k].sum(axis=0) * 0.25

    def push(row, k, vels, lam, new):
        return vels + (new - lam[row + k])[None] * 0.5, lam.at[row + k].set(new)

    rows = tuple(sweeps.ImpulseRow(row, functools.partial(accumulated, row), functools.partial(push, row))
                 for row in (0, 2))

    def run(limit):
        monkeypatch.setattr(sweeps, "FUSED_POINTS", limit)
        solve = jax2d.jit(lambda vel, imp: sweeps.sweep(
            layout, vel, lambda v, lam, points, c: sweeps.for_points(points, rows, v, lam), const, imp, plan))
        return solve(vel, impulses)

    (small_vel, small), (large_vel, large) = run(10 ** 6), run(0)
    np.testing.assert_allclose(np.asarray(small), np.asarray(large), rtol=1e-6, atol=1e-6)
    for s, g in zip(small_vel, large_vel, strict=True):
        np.testing.assert_allclose(np.asarray(s), np.asarray(g), rtol=1e-6, atol=1e-6)
    assert not np.allclose(np.asarray(small), np.asarray(impulses))
