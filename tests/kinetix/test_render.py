"""The pixel renderer: colours by role and binding, rotation lines, layering, batching and PNG thumbnails."""

import dataclasses
import io

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

import jax2d
from jax2d import scene
from kinetix.level import ROLE_BLUE, ROLE_GREEN, empty_level, make_level
from kinetix.levels import load_level
from kinetix.render import (
    BACKGROUND,
    FIXED_JOINT_COLOUR,
    JOINT_OFF_COLOUR,
    MOTOR_BINDING_COLOURS,
    OUTLINE_COLOUR,
    ROTATION_LINE_SHADE,
    THRUSTER_BINDING_COLOURS,
    render_pixels,
    render_thumbnail_png,
    to_uint8,
)

WORLD = 5.0
GREEN = np.array([0, 204, 0]) / 255
BLUE = np.array([0, 102, 204]) / 255
FIXED_NONE = np.array([80, 80, 80]) / 255


def centre(i: int, resolution: int = 64) -> float:
    """World coordinate of the centre of pixel column i (or, for y, of row resolution - 1 - i)."""
    return (i + 0.5) * WORLD / resolution


def pixel(image, x: float, y: float) -> np.ndarray:
    """The pixel holding world point (x, y): row 0 is the top of the world."""
    res = image.shape[0]
    row = int((WORLD - y) / WORLD * res)
    col = int(x / WORLD * res)
    return np.asarray(image[row, col])


def darkest_near(image, x: float, y: float) -> np.ndarray:
    """The darkest of the 3 x 3 pixels around world point (x, y): a thin line may fall between pixel centres."""
    res = image.shape[0]
    row, col = int((WORLD - y) / WORLD * res), int(x / WORLD * res)
    patch = np.asarray(image[row - 1 : row + 2, col - 1 : col + 2]).reshape(-1, 3)
    return patch[np.argmin(patch.sum(axis=1))]


def level_with(builder, size="s", roles=None, **bindings):
    """empty_level(size) plus what `builder(sim)` adds; roles as {body index: role}."""
    sim = builder(empty_level(size).sim)
    role_array = np.zeros(sim.num_bodies, np.int32)
    for index, role in (roles or {}).items():
        role_array[index] = role
    return make_level(sim, roles=role_array, **bindings)


def green_circle(angle=0.0, position=(2.5, 2.5), radius=0.5):
    def build(sim):
        sim, _ = scene.add_circle(sim, position, radius, angle=angle)
        return sim

    probe = empty_level("s").sim
    return level_with(build, roles={probe.num_polygons: ROLE_GREEN})


def test_shape_dtype_range_and_no_nan():
    for resolution in (16, 64, 65):
        image = np.asarray(render_pixels(green_circle(0.3), resolution))
        assert image.shape == (resolution, resolution, 3)
        assert image.dtype == np.float32
        assert np.all(np.isfinite(image))
        assert image.min() >= 0.0 and image.max() <= 1.0


def test_known_scene_circle_background_and_floor():
    image = render_pixels(green_circle(angle=0.0), 64)
    # Above the centre, away from the radius line (which points along +x at angle 0).
    np.testing.assert_allclose(pixel(image, 2.5, 2.75), GREEN, atol=0.02)
    np.testing.assert_allclose(pixel(image, 4.5, 4.5), BACKGROUND, atol=1e-6)
    np.testing.assert_allclose(pixel(image, 0.5, 4.5), BACKGROUND, atol=1e-6)
    # The floor is a fixed role-none polygon whose top is at y = 0.4: darker grey, and y up means bottom rows.
    np.testing.assert_allclose(pixel(image, 2.5, 0.2), FIXED_NONE, atol=0.02)
    np.testing.assert_allclose(np.asarray(image[-1, 32]), FIXED_NONE, atol=0.02)
    np.testing.assert_allclose(np.asarray(image[0, 32]), BACKGROUND, atol=1e-6)


def test_y_up_maps_to_image_up():
    low, high = green_circle(position=(2.5, 1.5), radius=0.3), green_circle(position=(2.5, 4.0), radius=0.3)
    green_rows = []
    for level in (low, high):
        image = np.asarray(render_pixels(level, 64))
        mask = np.all(np.abs(image - GREEN) < 0.05, axis=-1)
        green_rows.append(np.nonzero(mask)[0].mean())
    # Centres 2.5 m apart: 32 rows at 64 px over 5 m, the higher one nearer row 0.
    assert green_rows[0] - green_rows[1] == pytest.approx(2.5 / WORLD * 64, abs=1.0)


@pytest.mark.parametrize("angle", [0.0, 0.7, 2.5, -2.0])
def test_rotation_line_follows_the_angle(angle):
    image = render_pixels(green_circle(angle=angle, radius=0.8), 128)
    direction = np.array([np.cos(angle), np.sin(angle)])
    ahead = darkest_near(image, *(np.array([2.5, 2.5]) + 0.5 * direction))
    behind = darkest_near(image, *(np.array([2.5, 2.5]) - 0.5 * direction))
    # The line is the body colour times the shade; anti-aliasing may leave its darkest pixel partly covered.
    assert GREEN[1] * ROTATION_LINE_SHADE - 0.03 < ahead[1] < GREEN[1] * 0.75
    assert ahead[0] < 0.02 and ahead[2] < 0.02
    np.testing.assert_allclose(behind, GREEN, atol=0.02)


def test_fixed_body_darker_than_dynamic_body():
    def build(sim):
        sim, _ = scene.add_rectangle(sim, (1.5, 2.5), 1.0, 1.0, fixed=True)
        sim, _ = scene.add_rectangle(sim, (38 * WORLD / 64 + 0.5, 2.5), 1.0, 1.0)  # left edge on a pixel border
        return sim

    walls = 4
    level = level_with(build, size="m", roles={walls: ROLE_BLUE, walls + 1: ROLE_BLUE})
    image = render_pixels(level, 64)
    fixed, dynamic = pixel(image, 1.5, 2.5), pixel(image, 3.5, 2.5)
    np.testing.assert_allclose(dynamic, BLUE, atol=0.02)
    np.testing.assert_allclose(fixed, BLUE * 0.5, atol=0.02)
    # A dark outline 1 px wide just inside the box's left edge, background just outside.
    np.testing.assert_allclose(pixel(image, centre(38), 2.5), OUTLINE_COLOUR, atol=0.02)
    np.testing.assert_allclose(pixel(image, centre(37), 2.5), BACKGROUND, atol=0.02)


def test_later_slots_drawn_on_top():
    def build(sim):
        sim, _ = scene.add_rectangle(sim, (2.5, 2.5), 2.0, 2.0, fixed=True)
        sim, _ = scene.add_circle(sim, (2.5, 2.5), 0.5)
        return sim

    probe = empty_level("s").sim
    level = level_with(build, roles={4: ROLE_BLUE, probe.num_polygons: ROLE_GREEN})
    image = render_pixels(level, 64)
    np.testing.assert_allclose(pixel(image, 2.5, 2.75), GREEN, atol=0.02)  # circle (later slot) over the box
    np.testing.assert_allclose(pixel(image, 3.2, 3.2), BLUE * 0.5, atol=0.02)  # box outside the circle


def joint_level(binding=0, motor_on=True, fixed=False):
    anchor = (centre(32), centre(31))  # a pixel centre at 64 px

    def build(sim):
        sim, box = scene.add_rectangle(sim, (2.5, 2.5), 1.6, 1.6)
        sim, ball = scene.add_circle(sim, anchor, 0.4)
        if fixed:
            sim, _ = scene.add_fixed_joint(sim, box, ball, anchor)
        else:
            sim, _ = scene.add_revolute_joint(sim, box, ball, anchor, motor_on=motor_on)
        return sim

    return level_with(build, motor_bindings=[binding]), anchor


@pytest.mark.parametrize("binding", range(4))
def test_joint_disc_coloured_by_binding(binding):
    level, anchor = joint_level(binding)
    np.testing.assert_allclose(pixel(render_pixels(level, 64), *anchor), MOTOR_BINDING_COLOURS[binding], atol=0.03)


def test_joint_colours_are_distinct_and_motor_off_and_weld_differ():
    colours = [tuple(pixel(render_pixels(joint_level(b)[0], 64), *joint_level(b)[1]).round(2)) for b in range(4)]
    off_level, anchor = joint_level(2, motor_on=False)
    weld_level, _ = joint_level(2, fixed=True)
    off = pixel(render_pixels(off_level, 64), *anchor)
    weld = pixel(render_pixels(weld_level, 64), *anchor)
    np.testing.assert_allclose(off, JOINT_OFF_COLOUR, atol=0.03)
    np.testing.assert_allclose(weld, FIXED_JOINT_COLOUR, atol=0.03)
    colours += [tuple(off.round(2)), tuple(weld.round(2))]
    assert len(set(colours)) == 6
    # Hues as documented: yellow, magenta, cyan, orange.
    y, m, c, o = (np.array(x) for x in colours[:4])
    assert y[0] > 0.8 and y[1] > 0.8 and y[2] < 0.2
    assert m[0] > 0.8 and m[2] > 0.8 and m[1] < 0.2
    assert c[1] > 0.8 and c[2] > 0.8 and c[0] < 0.2
    assert o[0] > 0.8 and 0.3 < o[1] < 0.7 and o[2] < 0.2


@pytest.mark.parametrize("binding", range(2))
@pytest.mark.parametrize("angle", [0.0, np.pi / 2, np.pi])
def test_thruster_points_along_its_force_in_its_binding_colour(binding, angle):
    res = 256
    anchor = np.array([centre(128, res), centre(127, res)])

    def build(sim):
        sim, box = scene.add_rectangle(sim, (2.0, 2.5), 1.0, 0.6)
        sim, _ = scene.add_thruster(sim, box, tuple(anchor), angle=angle)
        return sim

    image = render_pixels(level_with(build, thruster_bindings=[binding]), res)
    direction = np.array([np.cos(angle), np.sin(angle)])
    unit = WORLD / 64
    ahead, behind = pixel(image, *(anchor + 1.0 * unit * direction)), pixel(image, *(anchor - 1.6 * unit * direction))
    np.testing.assert_allclose(ahead, THRUSTER_BINDING_COLOURS[binding], atol=0.05)
    assert np.abs(behind - THRUSTER_BINDING_COLOURS[binding]).max() > 0.3


def test_inactive_slots_are_never_drawn():
    level, _ = joint_level(1)
    b, j = level.sim.bodies, level.sim.joints
    hidden = dataclasses.replace(
        level.sim,
        bodies=dataclasses.replace(b, active=b.active.at[4:].set(False)),
        joints=dataclasses.replace(j, active=jnp.zeros_like(j.active)),
    )
    image = render_pixels(dataclasses.replace(level, sim=hidden), 64)
    np.testing.assert_allclose(image, render_pixels(empty_level("s"), 64), atol=1e-6)
    assert not np.allclose(render_pixels(level, 64), image, atol=0.1)


def test_vmap_and_jit_equal_individual_renders():
    levels = [green_circle(angle=a, position=(1.0 + a, 2.0), radius=0.3 + 0.2 * a) for a in (0.0, 0.5, 1.5)]
    levels.append(joint_level(3)[0])
    singles = np.stack([render_pixels(level, 48) for level in levels])
    batch = jax.tree.map(lambda *xs: jnp.stack(xs), *levels)
    batched = jax2d.jit(jax.vmap(lambda level: render_pixels(level, 48)))(batch)
    np.testing.assert_allclose(batched, singles, atol=1e-5)
    assert len({to_uint8(s).tobytes() for s in singles}) == len(levels)


def test_world_window_shifts_the_image():
    level = green_circle(angle=0.4, position=(2.2, 2.0))
    image = np.asarray(render_pixels(level, 50))  # 0.1 m pixels
    shifted = np.asarray(render_pixels(level, 50, world=(1.0, -0.5, 6.0, 4.5)))  # 1 m right, 0.5 m down
    np.testing.assert_allclose(shifted[:-5, :-10], image[5:, 10:], atol=1e-4)


def test_bad_arguments_raise():
    with pytest.raises(ValueError, match="world"):
        render_pixels(green_circle(), 32, world=(0.0, 0.0, -1.0, 5.0))
    with pytest.raises(ValueError, match="resolution"):
        render_pixels(green_circle(), 0)


def test_thumbnail_png_decodes_to_the_render():
    level = green_circle(angle=1.0)
    png = render_thumbnail_png(level, size=96)
    decoded = Image.open(io.BytesIO(png))
    assert decoded.format == "PNG" and decoded.size == (96, 96) and decoded.mode == "RGB"
    np.testing.assert_array_equal(np.asarray(decoded), to_uint8(render_pixels(level, 96)))


def test_shared_public_level_renders(shared_dir):
    path = shared_dir / "kinetix-levels" / "m" / "h3_car_thrust.json"
    level = load_level(path).level
    png = render_thumbnail_png(level, 256)
    with open("/tmp/render_check.png", "wb") as out:  # to look at by eye
        out.write(png)
    image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")) / 255.0
    assert np.isfinite(image).all()
    # Every role present among active bodies shows up with its colour (fixed bodies at half brightness).
    roles = np.asarray(level.roles)[np.asarray(level.sim.bodies.active)]
    static = np.asarray(level.sim.bodies.inv_mass == 0)[np.asarray(level.sim.bodies.active)]
    palette = np.array([[160, 160, 160], [0, 204, 0], [0, 102, 204], [255, 102, 102]]) / 255
    for role, fixed in {(int(r), bool(s)) for r, s in zip(roles, static, strict=True)}:
        colour = palette[role] * (0.5 if fixed and role else 1.0) if not (fixed and role == 0) else FIXED_NONE
        share = np.mean(np.all(np.abs(image - colour) < 0.02, axis=-1))
        assert share > 0.001, f"role {role} (fixed={fixed}) not visible"
    assert np.mean(np.all(np.abs(image - BACKGROUND) < 0.01, axis=-1)) > 0.5


def test_non_finite_slot_is_skipped_not_spread():
    level = green_circle(angle=0.3)
    bodies = level.sim.bodies
    broken = dataclasses.replace(bodies, position=bodies.position.at[level.sim.num_polygons, 0].set(jnp.nan))
    image = np.asarray(render_pixels(dataclasses.replace(level, sim=dataclasses.replace(level.sim, bodies=broken)), 64))
    assert np.all(np.isfinite(image))
    np.testing.assert_allclose(image, render_pixels(empty_level("s"), 64), atol=1e-6)
    batched = jax.vmap(lambda lv: render_pixels(lv, 64))(jax.tree.map(lambda x: x[None], level))
    assert np.all(np.isfinite(np.asarray(batched)))
