"""A JAX pixel renderer for levels: pixel observations and gallery thumbnails.

    image = render_pixels(level, 64)                      # (64, 64, 3) float32 RGB in [0, 1]
    images = jax.vmap(lambda l: render_pixels(l, 64))(levels)
    png = render_thumbnail_png(level, 256)                 # PNG bytes

Every body, joint and thruster slot becomes one layer: a convex shape (half-planes and a disc)
whose signed distance is computed for all pixels at once. Layers are drawn over each other by a
`lax.scan` in global slot order (polygons, then circles), then joints, then thrusters on top, so
memory is one image per level and the program is small for any size class. Inactive slots get
zero coverage. Edges are anti-aliased by the coverage clip(0.5 - sdf / pixel_size, 0, 1).

Look (colours as 0-255 RGB):
- background (250, 250, 250); bodies by role: none (160, 160, 160), green (0, 204, 0),
  blue (0, 102, 204), red (255, 102, 102); fixed (static) bodies darker: none (80, 80, 80),
  other roles at half brightness. Walls are ordinary fixed polygons and are drawn as such.
- a dark outline inside every body, 1 px thick at 64 px, growing as sqrt(resolution) (2 px at 256);
- circles show their rotation by a radius line from the centre along the body angle, in the
  body colour at 40 % brightness;
- joints: a disc at body a's anchor, coloured by motor binding when the motor is on (0 yellow,
  1 magenta, 2 cyan, 3 orange), white when off; fixed (weld) joints are dark grey squares;
- thrusters: a triangle at the anchor pointing along the force, coloured by thruster binding
  (0 orange-red (255, 69, 0), 1 purple (148, 0, 211)).
"""

from __future__ import annotations

import functools
import io

import jax
import jax.numpy as jnp
import numpy as np

import jax2d
from kinetix.level import Level


def _rgb(*colours) -> np.ndarray:
    """0-255 RGB triples as float32 in [0, 1]: (3,) for one colour, (n, 3) for several."""
    out = np.asarray(colours, np.float32) / 255.0
    return out[0] if len(colours) == 1 else out


BACKGROUND = _rgb((250, 250, 250))
ROLE_COLOURS = _rgb((160, 160, 160), (0, 204, 0), (0, 102, 204), (255, 102, 102))  # none, green, blue, red
FIXED_ROLE_COLOURS = _rgb((80, 80, 80), (0, 102, 0), (0, 51, 102), (127.5, 51, 51))  # role colours for static bodies
OUTLINE_COLOUR = _rgb((20, 20, 20))
ROTATION_LINE_SHADE = 0.4  # the radius line of a circle is its colour times this
# Motor bindings 0-3: yellow, magenta, cyan, orange.
MOTOR_BINDING_COLOURS = _rgb((255, 230, 0), (255, 0, 255), (0, 230, 230), (255, 140, 0))
JOINT_OFF_COLOUR = _rgb((255, 255, 255))
FIXED_JOINT_COLOUR = _rgb((100, 100, 100))
THRUSTER_BINDING_COLOURS = _rgb((255, 69, 0), (148, 0, 211))  # orange-red, purple

# Sizes of markers in units of 1/64 of the world width (pixels of a 64-pixel image), so they keep
# their size in the world at any resolution.
JOINT_RADIUS = 1.5
FIXED_JOINT_HALF_SIZE = 1.3
THRUSTER_LENGTH = 2.6  # apex ahead of the anchor along the force
THRUSTER_BACK = 0.8  # base behind the anchor
THRUSTER_HALF_WIDTH = 1.3
# Outlines (and the rotation line) are 1 pixel at 64 and grow with the square root of the
# resolution (2 pixels at 256): proportional growth would swallow thin bodies in big images.
OUTLINE_PIXELS_AT_64 = 1.0
JOINT_OUTLINE_FRACTION = 0.35  # joint and thruster outlines, as a fraction of the body outline

# One palette, so every layer's colour is one lookup: role colours, fixed role colours, motor
# bindings, joint off, weld joint, thruster bindings.
_PALETTE = np.concatenate([ROLE_COLOURS, FIXED_ROLE_COLOURS, MOTOR_BINDING_COLOURS, JOINT_OFF_COLOUR[None],
                           FIXED_JOINT_COLOUR[None], THRUSTER_BINDING_COLOURS])
_FIXED_ROLE, _MOTOR, _JOINT_OFF, _WELD, _THRUSTER = 4, 8, 12, 13, 14

_FAR = 1e6  # a distance that means "nowhere near": disabled half-planes and discs use it
_EPS = 1e-9


def _rotate(angle, x, y):
    c, s = jnp.cos(angle), jnp.sin(angle)
    return c * x - s * y, s * x + c * y


def _half_planes(vx, vy, n, width: int) -> jax.Array:
    """(K, width, 3) outward half-planes (nx, ny, c), nx * x + ny * y - c <= 0 inside, of K convex polygons.

    vx, vy: (K, V) world vertices, counter-clockwise; n: (K,) vertex counts. Edges past n, degenerate
    edges and padding become (0, 0, _FAR), which never wins the max that makes the signed distance.
    """
    V = vx.shape[-1]
    k = jnp.arange(V)
    wraps = k + 1 >= n[:, None]  # the last real edge closes back to vertex 0
    ex = jnp.where(wraps, vx[:, :1], jnp.roll(vx, -1, axis=1)) - vx
    ey = jnp.where(wraps, vy[:, :1], jnp.roll(vy, -1, axis=1)) - vy
    length = jnp.sqrt(ex * ex + ey * ey)
    valid = (k < n[:, None]) & (length > _EPS)
    inv = jnp.where(valid, 1.0 / jnp.maximum(length, _EPS), 0.0)
    nx, ny = ey * inv, -ex * inv  # outward normal of a counter-clockwise edge
    planes = jnp.stack([nx, ny, jnp.where(valid, nx * vx + ny * vy, _FAR)], axis=-1)
    padding = jnp.broadcast_to(jnp.array([0.0, 0.0, _FAR], jnp.float32), (vx.shape[0], width - V, 3))
    return jnp.concatenate([planes, padding], axis=1)


def _box(x, y):
    return jnp.stack([x.min(axis=1), x.max(axis=1), y.min(axis=1), y.max(axis=1)], axis=-1)


def _layers(level: Level, view, unit: float, outline: float) -> tuple[jax.Array, ...]:
    """One layer per body, joint and thruster slot, in drawing order: arrays with K = N + J + T rows.

    planes (K, width, 3) and disc (K, 3) = (cx, cy, r): the shape is where every half-plane and the
    disc hold (unused parts are disabled with _FAR). line (K, 3) = (dx, dy, on): circles draw a
    radius from the disc centre along (dx, dy). style (K, 5) = (r, g, b, outline width, visible),
    visible meaning active, finite and with a bounding box that meets `view`. unit: 1/64 of the world width.
    """
    sim = level.sim
    b, j, t = sim.bodies, sim.joints, sim.thrusters
    P, C, J, T = sim.num_polygons, sim.num_circles, sim.num_joints, sim.num_thrusters
    width = max(sim.max_vertices, 4)  # room for the weld-joint square
    f32 = jnp.float32
    pose = jnp.concatenate([b.position, b.angle[:, None]], axis=1)  # (N, 3): x, y, angle

    # Bodies in global index order: polygons, then circles.
    wx, wy = _rotate(b.angle[:P, None], b.vertices[..., 0], b.vertices[..., 1])
    wx, wy = wx + pose[:P, 0:1], wy + pose[:P, 1:2]
    real = jnp.arange(sim.max_vertices) < b.n_vertices[:, None]
    poly_box = _box(jnp.where(real, wx, wx[:, :1]), jnp.where(real, wy, wy[:, :1]))
    circle = pose[P:]
    r = b.radius[:, None]
    circle_box = jnp.concatenate([circle[:, :1] - r, circle[:, :1] + r, circle[:, 1:2] - r, circle[:, 1:2] + r], 1)
    static = b.inv_mass == 0.0
    body_colour = jnp.clip(level.roles, 0, 3) + jnp.where(static, _FIXED_ROLE, 0)

    # Joints at the world anchor of body a: a disc, or for a weld a square turned with body a.
    ja = pose[jnp.clip(j.a, 0, sim.num_bodies - 1)]
    jx, jy = _rotate(ja[:, 2], j.anchor_a[:, 0], j.anchor_a[:, 1])
    jx, jy = jx + ja[:, 0], jy + ja[:, 1]
    side = ja[:, 2:3] + jnp.arange(4, dtype=f32) * (jnp.pi / 2)
    sx, sy = jnp.cos(side), jnp.sin(side)
    square = jnp.stack([sx, sy, sx * jx[:, None] + sy * jy[:, None] + FIXED_JOINT_HALF_SIZE * unit], axis=-1)
    square = jnp.concatenate([square, jnp.broadcast_to(jnp.array([0.0, 0.0, _FAR], f32), (J, width - 4, 3))], 1)
    joint_planes = jnp.where(j.fixed[:, None, None], square, jnp.array([0.0, 0.0, _FAR], f32))
    joint_disc = jnp.stack([jx, jy, jnp.where(j.fixed, _FAR, JOINT_RADIUS * unit)], axis=-1)
    reach = max(JOINT_RADIUS, np.sqrt(2.0) * FIXED_JOINT_HALF_SIZE) * unit
    joint_box = jnp.stack([jx - reach, jx + reach, jy - reach, jy + reach], axis=-1)
    binding = _MOTOR + jnp.clip(level.motor_bindings, 0, 3)
    joint_colour = jnp.where(j.fixed, _WELD, jnp.where(j.motor_on, binding, _JOINT_OFF))

    # Thrusters: a triangle in the thruster's frame (x along the force), placed at its world anchor.
    tb = pose[jnp.clip(t.body, 0, sim.num_bodies - 1)]
    tx, ty = _rotate(tb[:, 2], t.anchor[:, 0], t.anchor[:, 1])
    shape_x = unit * jnp.array([-THRUSTER_BACK, THRUSTER_LENGTH, -THRUSTER_BACK], f32)
    shape_y = unit * jnp.array([-THRUSTER_HALF_WIDTH, 0.0, THRUSTER_HALF_WIDTH], f32)
    vx, vy = _rotate((tb[:, 2] + t.angle)[:, None], shape_x, shape_y)
    vx, vy = vx + (tx + tb[:, 0])[:, None], vy + (ty + tb[:, 1])[:, None]
    thruster_colour = _THRUSTER + jnp.clip(level.thruster_bindings, 0, 1)

    no_planes = jnp.broadcast_to(jnp.array([0.0, 0.0, _FAR], f32), (C, width, 3))
    planes = jnp.concatenate([_half_planes(wx, wy, b.n_vertices, width), no_planes, joint_planes,
                              _half_planes(vx, vy, jnp.full((T,), 3, jnp.int32), width)])
    no_disc = jnp.array([0.0, 0.0, _FAR], f32)
    disc = jnp.concatenate([jnp.broadcast_to(no_disc, (P, 3)), jnp.concatenate([circle[:, :2], r], 1), joint_disc,
                            jnp.broadcast_to(no_disc, (T, 3))])
    line_on = jnp.concatenate([jnp.zeros(P, f32), jnp.ones(C, f32), jnp.zeros(J + T, f32)])
    line_angle = jnp.concatenate([jnp.zeros(P, f32), circle[:, 2], jnp.zeros(J + T, f32)])
    line = jnp.stack([jnp.cos(line_angle), jnp.sin(line_angle), line_on], axis=-1)

    x0, y0, x1, y1 = view
    box = jnp.concatenate([poly_box, circle_box, joint_box, _box(vx, vy)])
    in_view = (box[:, 1] > x0) & (box[:, 0] < x1) & (box[:, 3] > y0) & (box[:, 2] < y1)
    # A slot whose numbers are not finite is skipped rather than spreading NaN over the image.
    finite = jnp.isfinite(planes).all(axis=(1, 2)) & jnp.isfinite(disc).all(axis=1) & jnp.isfinite(line).all(axis=1)
    visible = jnp.concatenate([b.active, j.active, t.active]) & in_view & finite
    colour = jnp.asarray(_PALETTE)[jnp.concatenate([body_colour, joint_colour, thruster_colour])]
    outline_width = jnp.where(jnp.arange(P + C + J + T) < P + C, outline, JOINT_OUTLINE_FRACTION * outline)
    style = jnp.concatenate([colour, outline_width[:, None], visible[:, None].astype(f32)], axis=1)
    return planes, disc, line, style


def _render(level: Level, resolution: int, world: tuple[float, float, float, float]) -> jax.Array:
    x0, y0, x1, y1 = world
    unit = (x1 - x0) / 64.0
    pixel = max(x1 - x0, y1 - y0) / resolution  # the anti-aliasing width (pixels are square for a square world)
    outline = OUTLINE_PIXELS_AT_64 * pixel * float(np.sqrt(resolution / 64.0))
    centres = (np.arange(resolution, dtype=np.float32) + 0.5) / resolution
    px = jnp.asarray(x0 + centres * (x1 - x0), jnp.float32)[None, :]  # (1, W)
    py = jnp.asarray(y1 - centres * (y1 - y0), jnp.float32)[:, None]  # (H, 1): row 0 at the top

    # One layer at a time, "over" the image so far: memory stays one image whatever the number of
    # slots or the batch, and the program is the same size for every size class.
    def draw(image, layer):
        planes, (cx, cy, r), (dx, dy, line_on), style = layer
        fill, edge_width = style[:3], style[3]
        sdf = jnp.sqrt((px - cx) ** 2 + (py - cy) ** 2) - r
        for k in range(planes.shape[0]):  # a static handful (<= 8) of maxima: one elementwise loop
            nx, ny, c = planes[k]
            sdf = jnp.maximum(sdf, nx * px + (ny * py - c))  # the x and y parts are 1-D: one add per pixel
        alpha = jnp.clip(0.5 - sdf / pixel, 0.0, 1.0)
        edge = jnp.clip(0.5 + (sdf + edge_width) / pixel, 0.0, 1.0)  # 1 in the outline band inside the edge
        # Distance to the radius segment from the disc centre along (dx, dy).
        rx, ry = px - cx, py - cy
        along = jnp.clip(rx * dx + ry * dy, 0.0, r)
        off_line = jnp.sqrt((rx - along * dx) ** 2 + (ry - along * dy) ** 2)
        stroke = line_on * jnp.clip(0.5 - (off_line - 0.5 * outline) / pixel, 0.0, 1.0)
        shade = (1.0 - (1.0 - ROTATION_LINE_SHADE) * stroke) * (1.0 - edge)
        colour = fill[:, None, None] * shade + OUTLINE_COLOUR[:, None, None] * edge  # (3, H, W)
        return image + alpha * (colour - image)

    def draw_if_visible(image, layer):
        # Skips empty slots and shapes outside the view (for one level; under vmap both branches run).
        return jax.lax.cond(layer[3][4] > 0.5, draw, lambda image, _: image, image, layer), None

    view = (x0 - pixel, y0 - pixel, x1 + pixel, y1 + pixel)  # with room for anti-aliased edges
    background = jnp.broadcast_to(jnp.asarray(BACKGROUND)[:, None, None], (3, resolution, resolution))
    image, _ = jax.lax.scan(draw_if_visible, background, _layers(level, view, unit, outline))
    return jnp.clip(jnp.moveaxis(image, 0, -1), 0.0, 1.0)


_render_jit = jax2d.jit(_render, static_argnames=("resolution", "world"))


def render_pixels(level: Level, resolution: int = 64, *, world=(0.0, 0.0, 5.0, 5.0)) -> jax.Array:
    """The level as a (resolution, resolution, 3) float32 RGB image in [0, 1], row 0 at the top.

    `world` = (x_min, y_min, x_max, y_max) is the square of the world shown (default the 5 m x 5 m
    Kinetix box). `resolution` and `world` are static (each value compiles once); the level is
    traced, so this works under jit and vmap (for a batch: jax.vmap(lambda l: render_pixels(l, 64))).
    """
    world = tuple(float(v) for v in world)
    if len(world) != 4 or not (world[2] > world[0] and world[3] > world[1]):
        raise ValueError(f"world must be (x_min, y_min, x_max, y_max) with max > min, got {world}")
    if int(resolution) != resolution or resolution < 1:
        raise ValueError(f"resolution must be a positive integer, got {resolution!r}")
    return _render_jit(level, resolution=int(resolution), world=world)


def to_uint8(image) -> np.ndarray:
    """An image in [0, 1] as uint8 (rounded), on the host."""
    return np.round(np.clip(np.asarray(image, np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)


@functools.lru_cache(maxsize=1)
def _pillow():
    from PIL import Image  # imported on first use: rendering observations does not need Pillow

    return Image


def render_thumbnail_png(level: Level, size: int = 256) -> bytes:
    """A PNG (size x size, RGB) of the level, for the gallery."""
    buffer = io.BytesIO()
    _pillow().fromarray(to_uint8(render_pixels(level, size))).save(buffer, format="PNG", optimize=False)
    return buffer.getvalue()
