"""Narrow-phase tests: analytic manifolds, masking of padded vertices, batching and finiteness."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jax2d
from jax2d.collide import Manifold, collide_circles, collide_polygon_circle, collide_polygons

SPEC = 0.04  # speculative distance used throughout
TOL = 2e-5


def box(half_w: float, half_h: float, size: int = 8) -> tuple[np.ndarray, int]:
    """A counter-clockwise box centred at the origin, padded with garbage to `size` rows."""
    corners = [(-half_w, -half_h), (half_w, -half_h), (half_w, half_h), (-half_w, half_h)]
    return padded(corners, size), 4


def regular_polygon(n: int, radius: float, size: int = 8, phase: float = 0.0) -> tuple[np.ndarray, int]:
    """A regular n-gon with circumradius `radius`; vertex k sits at angle phase + 2 pi k / n."""
    angles = phase + 2.0 * np.pi * np.arange(n) / n
    return padded(np.stack([radius * np.cos(angles), radius * np.sin(angles)], axis=1), size), n


def padded(points, size: int) -> np.ndarray:
    """Stack points into a (size, 2) float32 array; padding rows hold values that must be ignored."""
    out = np.full((size, 2), 123.0, np.float32)
    out[: len(points)] = np.asarray(points, np.float32)
    return out


def valid_points(m: Manifold) -> tuple[np.ndarray, np.ndarray]:
    """Valid points and separations, sorted by x then y, as numpy arrays."""
    valid = np.asarray(m.valid)
    pts, seps = np.asarray(m.point)[valid], np.asarray(m.separation)[valid]
    order = np.lexsort((pts[:, 1], pts[:, 0])) if len(pts) else np.arange(0)
    return pts[order], seps[order]


def assert_finite(m: Manifold):
    for leaf in jax.tree.leaves(m):
        assert np.all(np.isfinite(np.asarray(leaf))), m


def rot(angle: float, v) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    v = np.asarray(v, np.float64)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


# ---------------------------------------------------------------- polygon vs polygon


def test_box_resting_on_box_two_points():
    ground, n_g = box(2.0, 0.5)
    crate, n_c = box(0.5, 0.5)
    overlap = 0.01
    m = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (0.3, 1.0 - overlap), 0.0, crate, n_c, SPEC)
    assert_finite(m)
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)
    pts, seps = valid_points(m)
    assert len(pts) == 2
    np.testing.assert_allclose(seps, [-overlap, -overlap], atol=TOL)
    # Midway between the crate's bottom (0.49) and the ground's top (0.5).
    np.testing.assert_allclose(pts, [[-0.2, 0.5 - overlap / 2], [0.8, 0.5 - overlap / 2]], atol=TOL)
    assert len(set(np.asarray(m.key).tolist())) == 2  # the two points have different keys


def test_swapping_the_pair_flips_the_normal():
    ground, n_g = box(2.0, 0.5)
    crate, n_c = box(0.5, 0.5)
    m = collide_polygons((0.3, 0.99), 0.0, crate, n_c, (0.0, 0.0), 0.0, ground, n_g, SPEC)
    np.testing.assert_allclose(m.normal, (0.0, -1.0), atol=TOL)
    pts, seps = valid_points(m)
    np.testing.assert_allclose(seps, [-0.01, -0.01], atol=TOL)
    np.testing.assert_allclose(pts[:, 1], [0.495, 0.495], atol=TOL)


def test_whole_stack_rotated():
    """Rotating both boxes and their offset together rotates the manifold and keeps separations."""
    ground, n_g = box(2.0, 0.5)
    crate, n_c = box(0.5, 0.5)
    theta = 0.7
    pos_b = rot(theta, (0.3, 0.98))
    m = collide_polygons((0.0, 0.0), theta, ground, n_g, pos_b, theta, crate, n_c, SPEC)
    np.testing.assert_allclose(m.normal, rot(theta, (0.0, 1.0)), atol=TOL)
    pts, seps = valid_points(m)
    np.testing.assert_allclose(seps, [-0.02, -0.02], atol=TOL)
    expected = sorted([tuple(rot(theta, (x, 0.49))) for x in (-0.2, 0.8)])
    np.testing.assert_allclose(pts, expected, atol=TOL)


def test_diamond_corner_on_box_gives_one_point():
    ground, n_g = box(2.0, 0.5)
    crate, n_c = box(0.5, 0.5)
    half_diag = 0.5 * math.sqrt(2.0)
    overlap = 0.015
    m = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (0.1, 0.5 + half_diag - overlap), math.pi / 4, crate, n_c, SPEC)
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)
    pts, seps = valid_points(m)
    assert len(pts) == 1
    np.testing.assert_allclose(seps, [-overlap], atol=TOL)
    np.testing.assert_allclose(pts[0], (0.1, 0.5 - overlap / 2), atol=TOL)
    # Swapped, the reference face belongs to B (the ground): the normal still points from A to B.
    swapped = collide_polygons(
        (0.1, 0.5 + half_diag - overlap), math.pi / 4, crate, n_c, (0.0, 0.0), 0.0, ground, n_g, SPEC
    )
    np.testing.assert_allclose(swapped.normal, (0.0, -1.0), atol=TOL)
    pts, seps = valid_points(swapped)
    np.testing.assert_allclose(seps, [-overlap], atol=TOL)
    np.testing.assert_allclose(pts[0], (0.1, 0.5 - overlap / 2), atol=TOL)
    assert int(np.max(swapped.key)) != int(np.max(m.key))


def test_separation_threshold_is_the_speculative_distance():
    ground, n_g = box(2.0, 0.5)
    crate, n_c = box(0.5, 0.5)
    far = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (0.0, 1.1), 0.0, crate, n_c, SPEC)
    assert_finite(far)
    assert not np.any(far.valid)
    assert np.all(np.asarray(far.key) == -1)
    near = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (0.0, 1.02), 0.0, crate, n_c, SPEC)
    _, seps = valid_points(near)
    np.testing.assert_allclose(seps, [0.02, 0.02], atol=TOL)  # speculative points, positive separation


def test_corner_near_miss_has_no_points():
    """Diagonally offset boxes whose faces do not face each other: clipping leaves nothing."""
    crate, n = box(0.5, 0.5)
    m = collide_polygons((0.0, 0.0), 0.0, crate, n, (1.01, 1.005), 0.0, crate, n, SPEC)
    assert_finite(m)
    assert not np.any(m.valid)


def test_side_by_side_boxes_horizontal_normal():
    crate, n = box(0.5, 0.5)
    m = collide_polygons((0.0, 0.0), 0.0, crate, n, (0.99, 0.2), 0.0, crate, n, SPEC)
    np.testing.assert_allclose(m.normal, (1.0, 0.0), atol=TOL)
    pts, seps = valid_points(m)
    np.testing.assert_allclose(seps, [-0.01, -0.01], atol=TOL)
    np.testing.assert_allclose(pts, [[0.495, -0.3], [0.495, 0.5]], atol=TOL)


def test_triangle_flat_on_box():
    ground, n_g = box(2.0, 0.5)
    tri = padded([(-0.5, -0.3), (0.5, -0.3), (0.0, 0.6)], 8)
    m = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (0.0, 0.5 + 0.3 - 0.02), 0.0, tri, 3, SPEC)
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)
    pts, seps = valid_points(m)
    np.testing.assert_allclose(seps, [-0.02, -0.02], atol=TOL)
    np.testing.assert_allclose(pts, [[-0.5, 0.49], [0.5, 0.49]], atol=TOL)


def test_triangle_apex_down_on_box():
    ground, n_g = box(2.0, 0.5)
    tri = padded([(0.0, -0.6), (0.5, 0.3), (-0.5, 0.3)], 8)
    m = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (0.25, 0.5 + 0.6 - 0.03), 0.0, tri, 3, SPEC)
    pts, seps = valid_points(m)
    assert len(pts) == 1
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)
    np.testing.assert_allclose(seps, [-0.03], atol=TOL)
    np.testing.assert_allclose(pts[0], (0.25, 0.485), atol=TOL)


def test_octagon_flat_on_box():
    radius = 0.6
    # Phase pi/8 puts an edge (between vertices 4 and 5 at angles 9pi/8 and 11pi/8) at the bottom.
    octagon, n_o = regular_polygon(8, radius, phase=math.pi / 8)
    apothem = radius * math.cos(math.pi / 8)
    half_edge = radius * math.sin(math.pi / 8)
    ground, n_g = box(2.0, 0.5)
    overlap = 0.012
    m = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (-0.4, 0.5 + apothem - overlap), 0.0, octagon, n_o, SPEC)
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)
    pts, seps = valid_points(m)
    np.testing.assert_allclose(seps, [-overlap, -overlap], atol=TOL)
    y = 0.5 - overlap / 2
    np.testing.assert_allclose(pts, [[-0.4 - half_edge, y], [-0.4 + half_edge, y]], atol=TOL)


def test_polygon_padding_is_ignored():
    tri3 = np.array([(-0.5, -0.3), (0.5, -0.3), (0.0, 0.6)], np.float32)
    tri8 = np.zeros((8, 2), np.float32)
    tri8[:3] = tri3
    tri8[3:] = [(1e6, -1e6), (np.nan, 3.0), (np.inf, -np.inf), (5.0, 5.0), (-40.0, 0.0)]
    ground, n_g = box(2.0, 0.5, size=4)
    pose = ((0.1, 0.75), 0.3)
    small = collide_polygons((0.0, 0.0), 0.0, ground, n_g, *pose, tri3, 3, SPEC)
    large = collide_polygons((0.0, 0.0), 0.0, ground, n_g, *pose, tri8, 3, SPEC)
    assert np.any(small.valid)
    assert_finite(large)
    for x, y in zip(jax.tree.leaves(small), jax.tree.leaves(large), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=1e-6)
    # Same for the triangle as polygon A against a circle.
    c_small = collide_polygon_circle(*pose, tri3, 3, (0.1, 1.2), 0.2, SPEC)
    c_large = collide_polygon_circle(*pose, tri8, 3, (0.1, 1.2), 0.2, SPEC)
    assert np.any(c_small.valid)
    for x, y in zip(jax.tree.leaves(c_small), jax.tree.leaves(c_large), strict=True):
        np.testing.assert_allclose(np.asarray(x), np.asarray(y), atol=1e-6)


def test_key_stable_while_sliding_and_changes_with_features():
    ground, n_g = box(2.0, 0.5)
    crate, n_c = box(0.5, 0.5)
    keys = [
        np.asarray(collide_polygons((0.0, 0.0), 0.0, ground, n_g, (x, 0.99), 0.0, crate, n_c, SPEC).key)
        for x in (-0.3, 0.0, 0.4)
    ]
    assert all(np.array_equal(k, keys[0]) for k in keys)
    assert np.all(keys[0] >= 0)
    # Resting on a side face instead touches different features.
    side = collide_polygons((0.0, 0.0), 0.0, ground, n_g, (2.49, 0.0), 0.0, crate, n_c, SPEC)
    assert not np.array_equal(np.asarray(side.key), keys[0])


# ---------------------------------------------------------------- polygon vs circle


def test_circle_on_box_face():
    ground, n_g = box(1.0, 0.5)
    m = collide_polygon_circle((0.0, 0.0), 0.0, ground, n_g, (0.3, 0.5 + 0.25 - 0.01), 0.25, SPEC)
    assert_finite(m)
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)
    assert np.asarray(m.valid).tolist() == [True, False]
    np.testing.assert_allclose(m.separation[0], -0.01, atol=TOL)
    np.testing.assert_allclose(m.point[0], (0.3, 0.495), atol=TOL)


def test_circle_on_rotated_box_face():
    ground, n_g = box(1.0, 0.5)
    theta, pos = -0.4, np.array([2.0, -1.0])
    centre = pos + rot(theta, (0.3, 0.5 + 0.25 + 0.02))
    m = collide_polygon_circle(pos, theta, ground, n_g, centre, 0.25, SPEC)
    np.testing.assert_allclose(m.normal, rot(theta, (0.0, 1.0)), atol=TOL)
    np.testing.assert_allclose(m.separation[0], 0.02, atol=TOL)
    np.testing.assert_allclose(m.point[0], pos + rot(theta, (0.3, 0.51)), atol=TOL)
    assert bool(m.valid[0])


def test_circle_at_box_corner_vertex_region():
    ground, n_g = box(1.0, 0.5)
    centre, r = np.array([1.2, 0.7]), 0.3
    m = collide_polygon_circle((0.0, 0.0), 0.0, ground, n_g, centre, r, SPEC)
    dist = 0.2 * math.sqrt(2.0)
    normal = np.array([1.0, 1.0]) / math.sqrt(2.0)
    np.testing.assert_allclose(m.normal, normal, atol=TOL)
    np.testing.assert_allclose(m.separation[0], dist - r, atol=TOL)
    np.testing.assert_allclose(m.point[0], centre - normal * (r + (dist - r) / 2), atol=TOL)
    assert bool(m.valid[0])
    face = collide_polygon_circle((0.0, 0.0), 0.0, ground, n_g, (0.3, 0.7), r, SPEC)
    assert int(m.key[0]) != int(face.key[0])  # vertex and face regions are different features


def test_circle_centre_inside_box():
    ground, n_g = box(1.0, 0.5)
    m = collide_polygon_circle((0.0, 0.0), 0.0, ground, n_g, (0.1, 0.4), 0.2, SPEC)
    assert_finite(m)
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)  # nearest face is the top
    np.testing.assert_allclose(m.separation[0], -0.1 - 0.2, atol=TOL)
    np.testing.assert_allclose(m.point[0], (0.1, (0.5 + 0.2) / 2), atol=TOL)
    left = collide_polygon_circle((0.0, 0.0), 0.0, ground, n_g, (-0.9, 0.0), 0.2, SPEC)
    np.testing.assert_allclose(left.normal, (-1.0, 0.0), atol=TOL)
    np.testing.assert_allclose(left.separation[0], -0.1 - 0.2, atol=TOL)


def test_circle_centre_at_polygon_centre_is_finite():
    ground, n_g = box(1.0, 0.5)
    m = collide_polygon_circle((0.0, 0.0), 0.0, ground, n_g, (0.0, 0.0), 0.0, SPEC)
    assert_finite(m)
    np.testing.assert_allclose(np.linalg.norm(m.normal), 1.0, atol=TOL)
    np.testing.assert_allclose(m.separation[0], -0.5, atol=TOL)


def test_circle_far_from_polygon_is_not_valid():
    ground, n_g = box(1.0, 0.5)
    m = collide_polygon_circle((0.0, 0.0), 0.0, ground, n_g, (3.0, 3.0), 0.5, SPEC)
    assert_finite(m)
    assert not np.any(m.valid)
    np.testing.assert_allclose(m.normal, np.array([2.0, 2.5]) / np.hypot(2.0, 2.5), atol=TOL)


def signed_distance_to_polygon(poly: np.ndarray, p: np.ndarray) -> float:
    """Reference implementation: boundary distance, negative inside (polygon in world frame)."""
    best = np.inf
    inside = True
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        e = b - a
        u = np.clip(np.dot(p - a, e) / np.dot(e, e), 0.0, 1.0)
        best = min(best, np.linalg.norm(p - (a + u * e)))
        inside &= (e[0] * (p[1] - a[1]) - e[1] * (p[0] - a[0])) >= 0.0
    return -best if inside else best


def test_polygon_circle_separation_matches_brute_force():
    rng = np.random.default_rng(1)
    for _ in range(40):
        n = int(rng.integers(3, 9))
        verts, _ = regular_polygon(n, rng.uniform(0.3, 1.5), phase=rng.uniform(0, 2 * np.pi))
        pos, angle = rng.uniform(-2, 2, 2), rng.uniform(-np.pi, np.pi)
        centre, r = pos + rng.uniform(-2.5, 2.5, 2), rng.uniform(0.0, 0.8)
        m = collide_polygon_circle(pos, angle, verts, n, centre, r, 10.0)
        world = np.array([pos + rot(angle, v) for v in verts[:n].astype(np.float64)])
        expected = signed_distance_to_polygon(world, centre) - r
        np.testing.assert_allclose(m.separation[0], expected, atol=1e-4)
        # The normal points from the polygon surface point to the circle centre.
        surface = np.asarray(m.point[0]) - np.asarray(m.normal) * expected / 2
        np.testing.assert_allclose(signed_distance_to_polygon(world, surface), 0.0, atol=1e-4)


# ---------------------------------------------------------------- circle vs circle


def test_circles_overlap_and_separate():
    m = collide_circles((0.0, 0.0), 1.0, (1.5, 0.0), 0.7, SPEC)
    np.testing.assert_allclose(m.normal, (1.0, 0.0), atol=TOL)
    np.testing.assert_allclose(m.separation[0], -0.2, atol=TOL)
    np.testing.assert_allclose(m.point[0], (0.9, 0.0), atol=TOL)  # midway between 1.0 and 0.8
    assert np.asarray(m.valid).tolist() == [True, False]
    far = collide_circles((0.0, 0.0), 1.0, (0.0, -2.0), 0.5, SPEC)
    np.testing.assert_allclose(far.normal, (0.0, -1.0), atol=TOL)
    assert not np.any(far.valid)
    assert_finite(far)


def test_coincident_circles_are_finite():
    m = collide_circles((1.0, 2.0), 0.5, (1.0, 2.0), 0.25, SPEC)
    assert_finite(m)
    np.testing.assert_allclose(m.normal, (0.0, 1.0), atol=TOL)
    np.testing.assert_allclose(m.separation[0], -0.75, atol=TOL)
    zero = collide_circles((0.0, 0.0), 0.0, (0.0, 0.0), 0.0, SPEC)
    assert_finite(zero)
    assert bool(zero.valid[0])


# ---------------------------------------------------------------- properties shared by all pairs


@pytest.mark.parametrize("direction_deg", range(0, 360, 45))
def test_normal_points_from_a_to_b(direction_deg):
    d = np.array([math.cos(math.radians(direction_deg)), math.sin(math.radians(direction_deg))])
    square, n_s = box(0.5, 0.5)
    octagon, n_o = regular_polygon(8, 0.5)
    for verts_a, n_a, verts_b, n_b in [(square, n_s, octagon, n_o), (octagon, n_o, square, n_s)]:
        m = collide_polygons((0.0, 0.0), 0.1, verts_a, n_a, 0.95 * d, -0.2, verts_b, n_b, SPEC)
        assert np.dot(m.normal, d) > 0.5
        assert np.any(m.valid)
    m = collide_polygon_circle((0.0, 0.0), 0.3, square, n_s, 0.9 * d, 0.4, SPEC)
    assert np.dot(m.normal, d) > 0.5
    m = collide_circles((0.0, 0.0), 0.5, 0.9 * d, 0.5, SPEC)
    np.testing.assert_allclose(m.normal, d, atol=TOL)


def random_pairs(rng: np.random.Generator, count: int, coincident: float, size: int = 8) -> dict[str, np.ndarray]:
    """Random poses and regular polygons (some of zero size); a `coincident` fraction of pairs share a centre."""
    n = rng.integers(3, size + 1, (2, count)).astype(np.int32)
    verts = np.full((2, count, size, 2), np.nan, np.float32)  # NaN padding must never leak
    for k in range(2):
        for i in range(count):
            verts[k, i] = regular_polygon(n[k, i], rng.uniform(0.0, 1.5), size, rng.uniform(0, 7))[0]
            verts[k, i, n[k, i] :] = np.nan
    verts[:, rng.random(count) < 0.1, :, :] = 0.0  # some polygons collapsed to a point
    pos = rng.uniform(-2.0, 2.0, (2, count, 2)).astype(np.float32)
    same = rng.random(count) < coincident
    pos[1, same] = pos[0, same]
    return dict(
        pos=pos,
        angle=rng.uniform(-7, 7, (2, count)).astype(np.float32),
        verts=verts,
        n=n,
        radius=np.where(rng.random((2, count)) < 0.2, 0.0, rng.uniform(0, 1, (2, count))).astype(np.float32),
    )


BATCHED = {
    "polygons": jax2d.jit(jax.vmap(collide_polygons, in_axes=(0, 0, 0, 0, 0, 0, 0, 0, None))),
    "polygon_circle": jax2d.jit(jax.vmap(collide_polygon_circle, in_axes=(0, 0, 0, 0, 0, 0, None))),
    "circles": jax2d.jit(jax.vmap(collide_circles, in_axes=(0, 0, 0, 0, None))),
}


def batched_calls(p: dict[str, np.ndarray]):
    args = {
        "polygons": (p["pos"][0], p["angle"][0], p["verts"][0], p["n"][0], p["pos"][1], p["angle"][1])
        + (p["verts"][1], p["n"][1], SPEC),
        "polygon_circle": (p["pos"][0], p["angle"][0], p["verts"][0], p["n"][0], p["pos"][1], p["radius"][1], SPEC),
        "circles": (p["pos"][0], p["radius"][0], p["pos"][1], p["radius"][1], SPEC),
    }
    return args


def test_jit_vmap_matches_single_calls():
    # No coincident centres here: a circle centred in a regular polygon is an exact tie between
    # faces, which batched and single code may legitimately break differently.
    p = random_pairs(np.random.default_rng(7), 12, coincident=0.0)
    singles = {"polygons": collide_polygons, "polygon_circle": collide_polygon_circle, "circles": collide_circles}
    for name, args in batched_calls(p).items():
        batch = BATCHED[name](*args)
        for i in range(len(p["n"][0])):
            one = singles[name](*[a[i] if isinstance(a, np.ndarray) else a for a in args])
            for x, y in zip(jax.tree.leaves(batch), jax.tree.leaves(one), strict=True):
                np.testing.assert_allclose(np.asarray(x)[i], np.asarray(y), atol=1e-5, err_msg=name)


def test_random_batch_is_finite_and_well_formed():
    p = random_pairs(np.random.default_rng(3), 500, coincident=0.25)
    for name, args in batched_calls(p).items():
        m = BATCHED[name](*args)
        assert_finite(m)
        np.testing.assert_allclose(np.linalg.norm(np.asarray(m.normal), axis=-1), 1.0, atol=1e-5, err_msg=name)
        valid, sep, key = np.asarray(m.valid), np.asarray(m.separation), np.asarray(m.key)
        assert np.all(sep[valid] < SPEC) and np.all(sep[~valid] == np.float32(SPEC))
        assert np.all((key >= 0) == valid)
        assert m.key.dtype == jnp.int32 and m.valid.dtype == jnp.bool_
        assert m.point.shape == (500, 2, 2)
        if name != "polygons":
            assert not np.any(valid[:, 1])


def test_best_entry_is_argmax_and_max_with_ties_and_nans_as_numpy_has_them():
    from jax2d import collide

    rng = np.random.default_rng(3)
    values = rng.integers(0, 4, (8, 50)).astype(np.float32)  # many ties
    values[rng.random((8, 50)) < 0.05] = np.nan
    for largest, arg, best in ((True, np.argmax, np.max), (False, np.argmin, np.min)):
        index, value = collide._best(jnp.asarray(values), largest)
        np.testing.assert_array_equal(np.asarray(index), arg(values, axis=0))
        np.testing.assert_array_equal(np.asarray(value), best(values, axis=0))
