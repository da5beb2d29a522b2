"""Mass properties against closed-form results, and every polygon validation error."""

import numpy as np
import pytest

from jax2d.geometry import (
    GeometryError,
    circle_mass_properties,
    polygon_mass_properties,
    rectangle_vertices,
    regular_polygon_vertices,
    signed_area,
    validate_polygon,
)


def rotate(points, angle):
    c, s = np.cos(angle), np.sin(angle)
    return np.asarray(points) @ np.array([[c, s], [-s, c]])  # rows times R^T


@pytest.mark.parametrize("width,height,density", [(1.0, 1.0, 1.0), (2.0, 0.5, 3.0), (10.0, 0.1, 0.25)])
def test_rectangle_mass_and_inertia(width, height, density):
    mass, inertia, centroid = polygon_mass_properties(rectangle_vertices(width, height), density)
    expected_mass = density * width * height
    assert mass == pytest.approx(expected_mass, rel=1e-12)
    assert inertia == pytest.approx(expected_mass * (width**2 + height**2) / 12, rel=1e-12)
    np.testing.assert_allclose(centroid, 0.0, atol=1e-12)


def test_offset_and_rotated_rectangle_keeps_inertia_and_moves_centroid():
    offset = np.array([3.0, -2.0])
    verts = rotate(rectangle_vertices(2.0, 1.0), 0.7) + offset
    mass, inertia, centroid = polygon_mass_properties(verts, 2.0)
    assert mass == pytest.approx(4.0)
    assert inertia == pytest.approx(4.0 * (4.0 + 1.0) / 12)
    np.testing.assert_allclose(centroid, offset, atol=1e-12)


@pytest.mark.parametrize(
    "verts", [[(0, 0), (3, 0), (0, 6)], [(1, 1), (4, 2), (2, 5)], [(-2, 0), (2, 0), (0, np.sqrt(12))]]
)
def test_triangle_centroid_and_inertia(verts):
    v = np.array(verts, float)
    density = 1.5
    mass, inertia, centroid = polygon_mass_properties(v, density)
    (ax, ay), (bx, by) = v[1] - v[0], v[2] - v[0]
    area = 0.5 * abs(ax * by - ay * bx)
    sides_squared = sum(np.sum((v[i] - v[i - 1]) ** 2) for i in range(3))
    assert mass == pytest.approx(density * area)
    np.testing.assert_allclose(centroid, v.mean(axis=0), atol=1e-12)
    # Polar moment of a uniform triangle about its centroid: m (a^2 + b^2 + c^2) / 36.
    assert inertia == pytest.approx(mass * sides_squared / 36)


@pytest.mark.parametrize("n", range(3, 9))
def test_regular_polygon_closed_form(n):
    radius, density = 1.3, 2.0
    mass, inertia, centroid = polygon_mass_properties(regular_polygon_vertices(n, radius, angle=0.3), density)
    area = 0.5 * n * radius**2 * np.sin(2 * np.pi / n)
    assert mass == pytest.approx(density * area)
    assert inertia == pytest.approx(mass * radius**2 / 6 * (1 + 2 * np.cos(np.pi / n) ** 2))
    np.testing.assert_allclose(centroid, 0.0, atol=1e-12)


def test_regular_polygons_approach_the_circle():
    radius, density = 0.8, 1.0
    circle_mass, circle_inertia, _ = circle_mass_properties(radius, density)
    props = [polygon_mass_properties(regular_polygon_vertices(n, radius), density) for n in range(3, 9)]
    masses = np.array([p[0] for p in props])
    normalised_inertia = np.array([p[1] / (p[0] * radius**2) for p in props])
    # Inscribed polygons grow towards the disc, and I / (m r^2) rises towards the disc's 1/2.
    assert np.all(np.diff(masses) > 0) and np.all(masses < circle_mass)
    assert np.all(np.diff(normalised_inertia) > 0) and np.all(normalised_inertia < 0.5)
    assert masses[-1] == pytest.approx(circle_mass, rel=0.1)
    assert props[-1][1] == pytest.approx(circle_inertia, rel=0.2)


@pytest.mark.parametrize("radius,density", [(1.0, 1.0), (0.25, 4.0), (3.0, 0.5)])
def test_circle_mass_properties(radius, density):
    mass, inertia, centroid = circle_mass_properties(radius, density)
    assert mass == pytest.approx(np.pi * radius**2 * density)
    assert inertia == pytest.approx(mass * radius**2 / 2)
    np.testing.assert_array_equal(centroid, [0.0, 0.0])


def test_shape_builders_are_counter_clockwise_and_centred():
    rect = rectangle_vertices(3.0, 1.0)
    assert signed_area(rect) == pytest.approx(3.0)
    np.testing.assert_allclose(rect.mean(axis=0), 0.0)
    np.testing.assert_allclose(np.ptp(rect, axis=0), [3.0, 1.0])
    hexagon = regular_polygon_vertices(6, 2.0)
    assert signed_area(hexagon) > 0
    np.testing.assert_allclose(np.linalg.norm(hexagon, axis=1), 2.0)


def test_validate_accepts_and_returns_float64():
    out = validate_polygon([(0, 0), (1, 0), (0, 1)])
    assert out.dtype == np.float64 and out.shape == (3, 2)


PENTAGON = regular_polygon_vertices(5, 1.0)


@pytest.mark.parametrize(
    "verts,message",
    [
        ([(0, 0), (0, 1), (1, 0)], "counter-clockwise (y up); got clockwise order — reverse them"),
        ([(0, 0), (2, 0), (1, 0.5), (2, 2), (0, 2)], "not convex: vertex 2"),
        ([(0, 0), (1, 0), (2, 0)], "zero area"),
        ([(0, 0), (1, 0), (2, 1e-9)], "zero area"),
        (regular_polygon_vertices(8, 1.0).tolist() + [(0.0, -1.5)], "3 to 8 vertices, got 9"),
        ([(0, 0), (1, 0)], "3 to 8 vertices, got 2"),
        ([(0, 0), (1, np.nan), (0, 1)], "vertex 1 is not finite"),
        ([(0, 0), (1, 0), (np.inf, 1)], "vertex 2 is not finite"),
        ([(0, 0), (1, 0), (1, 0), (0, 1)], "vertex 2 repeats vertex 1"),
        ([(0, 0), (1, 0), (1, 1), (0, 1), (0, 0)], "vertex 4 repeats vertex 0"),
        (PENTAGON[[0, 2, 4, 1, 3]], "self-intersecting"),
        ([0, 1, 2, 3], "shape (n, 2)"),
        ([("a", "b"), (1, 0), (0, 1)], "must be numbers"),
    ],
)
def test_validate_polygon_errors(verts, message):
    with pytest.raises(GeometryError) as info:
        validate_polygon(verts)
    assert message in str(info.value)
    assert isinstance(info.value, ValueError)


@pytest.mark.parametrize(
    "call,message",
    [
        (lambda: circle_mass_properties(-1.0, 1.0), "radius must be > 0, got -1.0"),
        (lambda: circle_mass_properties(0.0, 1.0), "radius must be > 0"),
        (lambda: circle_mass_properties(1.0, -2.0), "density must be > 0, got -2.0"),
        (lambda: circle_mass_properties(np.nan, 1.0), "radius must be finite"),
        (lambda: polygon_mass_properties(rectangle_vertices(1, 1), 0.0), "density must be > 0"),
        (lambda: polygon_mass_properties(rectangle_vertices(1, 1), np.inf), "density must be finite"),
        (lambda: rectangle_vertices(-1.0, 1.0), "width must be > 0"),
        (lambda: rectangle_vertices(1.0, 0.0), "height must be > 0"),
        (lambda: regular_polygon_vertices(9, 1.0), "3 to 8 sides, got 9"),
        (lambda: regular_polygon_vertices(5, -1.0), "radius must be > 0"),
    ],
)
def test_value_errors_say_what_is_wrong(call, message):
    with pytest.raises(GeometryError) as info:
        call()
    assert message in str(info.value)
