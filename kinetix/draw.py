"""The human-facing renderer: numpy + Pillow, fast and crisp (not the JAX observation renderer, kinetix.render).

    view = View(width, height)                 # the canvas size; the 5 m x 5 m world is letterboxed into it
    rgb = level_frame(level, view)             # (height, width, 3) uint8: the level as the browser shows it
    rgb, motors, thrusters = draw_scene(scene_of(level), view)   # the same, with the bindings drawn

The browser's play frames (server.play.draw adds the editor overlay, HUD, legend and banners on top) and
`kinetix.gym`'s rgb_array render both come from here, so they look the same. Shapes are drawn at 2x and reduced to
1x by Pillow's box filter, which anti-aliases every edge at a fraction of the cost of per-pixel coverage. Colours
follow kinetix.render so the editor, thumbnails and observations look alike.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

import numpy as np
from PIL import Image, ImageDraw

WORLD = (0.0, 0.0, 5.0, 5.0)  # the visible world box x0, y0, x1, y1 (metres)
SUPERSAMPLE = 2

BACKGROUND = (250, 250, 250)
LETTERBOX = (226, 228, 232)
ROLE = [(160, 160, 160), (0, 204, 0), (0, 102, 204), (255, 102, 102)]  # none, green, blue, red
FIXED_ROLE = [(80, 80, 80), (0, 102, 0), (0, 51, 102), (128, 51, 51)]  # static bodies darker
OUTLINE = (20, 20, 20)
MOTOR_COLOURS = [(255, 200, 0), (230, 0, 230), (0, 200, 210), (255, 120, 0)]  # motor bindings 0-3
THRUSTER_COLOURS = [(255, 69, 0), (148, 0, 211)]  # thruster bindings 0-1
JOINT_OFF = (255, 255, 255)
WELD = (100, 100, 100)


@dataclasses.dataclass(frozen=True)
class View:
    """Letterboxed mapping between the canvas (width x height pixels) and the world box."""

    width: int = 512
    height: int = 512
    world: tuple[float, float, float, float] = WORLD

    @property
    def scale(self) -> float:  # pixels per metre, the same on both axes so shapes are never stretched
        x0, y0, x1, y1 = self.world
        return min(self.width / (x1 - x0), self.height / (y1 - y0))

    @property
    def origin(self) -> tuple[float, float]:  # pixel position of the world's top-left corner
        x0, y0, x1, y1 = self.world
        s = self.scale
        return (self.width - s * (x1 - x0)) / 2, (self.height - s * (y1 - y0)) / 2

    def to_pixel(self, x: float, y: float) -> tuple[float, float]:
        ox, oy = self.origin
        return ox + (x - self.world[0]) * self.scale, oy + (self.world[3] - y) * self.scale

    def to_world(self, u: float, v: float) -> tuple[float, float]:
        """World metres of a viser screen position (u, v in 0..1 from the top-left corner)."""
        ox, oy = self.origin
        s = self.scale
        return self.world[0] + (u * self.width - ox) / s, self.world[3] - (v * self.height - oy) / s

    def to_screen(self, x: float, y: float) -> tuple[float, float]:
        px, py = self.to_pixel(x, y)
        return px / self.width, py / self.height


@dataclasses.dataclass
class Scene:
    """The numbers the renderer needs from a Level, as numpy arrays (pulled from JAX once per frame)."""

    position: np.ndarray
    angle: np.ndarray
    active: np.ndarray
    static: np.ndarray
    roles: np.ndarray
    vertices: np.ndarray
    n_vertices: np.ndarray
    radius: np.ndarray
    joint_a: np.ndarray
    joint_anchor: np.ndarray
    joint_active: np.ndarray
    joint_fixed: np.ndarray
    motor_on: np.ndarray
    motor_binding: np.ndarray
    thruster_body: np.ndarray
    thruster_anchor: np.ndarray
    thruster_angle: np.ndarray
    thruster_active: np.ndarray
    thruster_binding: np.ndarray


def scene_of(level, static_from: Scene | None = None, pose: tuple | None = None) -> Scene:
    """A Scene from a kinetix Level (single, not batched).

    `static_from`: a Scene of the same play. Only positions and angles change while a level plays, so just those
    two arrays are fetched and the rest is shared (one transfer instead of 19 per frame). `pose`: those two as
    host arrays already (server.play.steps.Motion fetched them with the step), so nothing is transferred.
    """
    import jax

    if static_from is not None:
        if pose is not None:
            position, angle = pose
        else:
            position, angle = jax.device_get((level.sim.bodies.position, level.sim.bodies.angle))
        return dataclasses.replace(static_from, position=np.asarray(position), angle=np.asarray(angle))

    b, j, t = level.sim.bodies, level.sim.joints, level.sim.thrusters
    arrays = jax.device_get((b.position, b.angle, b.active, b.inv_mass, level.roles, b.vertices, b.n_vertices,
                             b.radius, j.a, j.anchor_a, j.active, j.fixed, j.motor_on, level.motor_bindings,
                             t.body, t.anchor, t.angle, t.active, level.thruster_bindings))
    a = [np.asarray(x) for x in arrays]
    return Scene(a[0], a[1], a[2], a[3] == 0.0, a[4], a[5], a[6], a[7], a[8], a[9], a[10], a[11], a[12], a[13],
                 a[14], a[15], a[16], a[17], a[18])


def _rot(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s], [s, c]])


def _darker(colour, factor: float = 0.4):
    return tuple(int(c * factor) for c in colour)


_STATIC_CACHE: dict = {}  # (view, static-body bytes) -> (2x image, 1x array); static bodies never move in play
_STATIC_CACHE_SIZE = 8


def _body_ops(scene: Scene, indices, px, s: float, outline: int) -> list:
    """Drawing operations (method name, args, kwargs, pixel points) for these bodies."""
    ops = []
    n_poly = scene.vertices.shape[0]
    for i in indices:
        colour = (FIXED_ROLE if scene.static[i] else ROLE)[int(np.clip(scene.roles[i], 0, 3))]
        pos, ang = scene.position[i], float(scene.angle[i])
        if i < n_poly:
            pts = px(scene.vertices[i, : int(scene.n_vertices[i])] @ _rot(ang).T + pos)
            ops.append(("polygon", (pts,), {"fill": colour, "outline": OUTLINE, "width": outline}, pts))
        else:
            r = float(scene.radius[i - n_poly]) * s
            cx, cy = px(pos[None])[0]
            box = [(cx - r, cy - r), (cx + r, cy + r)]
            ops.append(("ellipse", (box,), {"fill": colour, "outline": OUTLINE, "width": outline}, box))
            ops.append(("line", ([(cx, cy), (cx + r * math.cos(ang), cy - r * math.sin(ang))],),
                        {"fill": _darker(colour), "width": outline}, []))
    return ops


def _static_layer(scene: Scene | None, big: View, px, s: float, outline: int) -> tuple[Image.Image, np.ndarray]:
    static = np.flatnonzero(scene.active & scene.static) if scene is not None else np.zeros(0, int)
    key: tuple = (big, static.tobytes())
    if scene is not None:
        key += tuple(np.ascontiguousarray(a[static]).tobytes() for a in (scene.position, scene.angle, scene.roles))
        key += (scene.vertices.tobytes(), scene.radius.tobytes())
    hit = _STATIC_CACHE.get(key)
    if hit is not None:
        return hit
    image = Image.new("RGB", (big.width, big.height), LETTERBOX)
    draw = ImageDraw.Draw(image)
    ox, oy = big.origin
    x0, y0, x1, y1 = big.world
    draw.rectangle([ox, oy, ox + s * (x1 - x0), oy + s * (y1 - y0)], fill=BACKGROUND)
    if scene is not None:
        for name, args, kwargs, _ in _body_ops(scene, static, px, s, outline):
            getattr(draw, name)(*args, **kwargs)
    if len(_STATIC_CACHE) >= _STATIC_CACHE_SIZE:
        _STATIC_CACHE.pop(next(iter(_STATIC_CACHE)))
    small = np.asarray(image.reduce(SUPERSAMPLE))
    small.flags.writeable = False  # shared by every frame of this view: frames start from a copy
    _STATIC_CACHE[key] = (image, small)
    return _STATIC_CACHE[key]


def draw_scene(scene: Scene | None, view: View, extra_ops: Callable | None = None
               ) -> tuple[np.ndarray, set[int], set[int]]:
    """(frame, motor bindings drawn, thruster bindings drawn): an (height, width, 3) uint8 RGB frame of the scene.

    extra_ops(px, scale) -> drawing operations (method name, args, kwargs, pixel points) drawn over the scene, with
    `px` mapping world points (n, 2) to supersampled pixels and `scale` the supersampled pixels per metre (the
    editor's overlay). Static bodies are drawn once per view into a cached layer; per frame only the box around the
    moving bodies, joints, thrusters and extra operations is drawn at 2x, reduced and pasted, which keeps a frame
    near 1-2 ms. The frame is a numpy array: a Pillow RGB image stores 4 bytes a pixel, so copying the whole frame
    through Pillow and back cost more than drawing it.
    """
    ss = SUPERSAMPLE
    big = View(view.width * ss, view.height * ss, view.world)
    ox, oy = big.origin
    s = big.scale
    x0, y1 = view.world[0], view.world[3]

    def px(points: np.ndarray) -> list[tuple[float, float]]:  # world (n, 2) -> supersampled pixels
        return [(ox + (p[0] - x0) * s, oy + (y1 - p[1]) * s) for p in np.asarray(points, float)]

    outline = max(1, round(s * 0.012))
    base_big, base_small = _static_layer(scene, big, px, s, outline)
    ops: list = []
    used_motor, used_thruster = set(), set()
    if scene is not None:
        ops += _body_ops(scene, np.flatnonzero(scene.active & ~scene.static), px, s, outline)
        ops += _joint_thruster_ops(scene, px, s, outline, used_motor, used_thruster)
    if extra_ops is not None:
        ops += extra_ops(px, s)
    frame = base_small.copy()
    points = [p for op in ops for p in op[3]]
    if points:
        xs, ys = [p[0] for p in points], [p[1] for p in points]
        pad = 4 * outline + 4
        left = max(0, int(min(xs) - pad) // ss * ss)
        top = max(0, int(min(ys) - pad) // ss * ss)
        right = min(big.width, (int(max(xs) + pad) // ss + 1) * ss)
        bottom = min(big.height, (int(max(ys) + pad) // ss + 1) * ss)
        if right > left and bottom > top:
            patch = base_big.crop((left, top, right, bottom))
            draw = ImageDraw.Draw(patch)
            for name, args, kwargs, _ in ops:
                getattr(draw, name)(*_shift(args, -left, -top), **kwargs)
            small = np.asarray(patch.reduce(ss))
            frame[top // ss:top // ss + small.shape[0], left // ss:left // ss + small.shape[1]] = small
    return frame, used_motor, used_thruster


def level_frame(level, view: View | None = None) -> np.ndarray:
    """An (height, width, 3) uint8 RGB frame of a kinetix Level (single, not batched) as the browser draws it,
    without the browser's text (default view: 512 x 512)."""
    return draw_scene(scene_of(level), view or View())[0]


def _shift(args: tuple, dx: float, dy: float) -> tuple:
    """Drawing-call arguments with every (x, y) point moved by (dx, dy)."""
    (points,) = args
    return ([(x + dx, y + dy) for x, y in points],)


def _joint_thruster_ops(scene: Scene, px, s: float, outline: int, used_motor: set, used_thruster: set) -> list:
    ops = []
    r = 0.07 * s
    for k in np.flatnonzero(scene.joint_active):
        a = int(scene.joint_a[k])
        cx, cy = px((scene.joint_anchor[k] @ _rot(float(scene.angle[a])).T + scene.position[a])[None])[0]
        box = [(cx - r, cy - r), (cx + r, cy + r)]
        if scene.joint_fixed[k]:
            ops.append(("rectangle", (box,), {"fill": WELD, "outline": OUTLINE, "width": outline}, box))
            continue
        colour = JOINT_OFF
        if scene.motor_on[k]:
            binding = int(np.clip(scene.motor_binding[k], 0, 3))
            colour = MOTOR_COLOURS[binding]
            used_motor.add(binding)
        ops.append(("ellipse", (box,), {"fill": colour, "outline": OUTLINE, "width": outline}, box))
    for k in np.flatnonzero(scene.thruster_active):
        body = int(scene.thruster_body[k])
        anchor = scene.thruster_anchor[k] @ _rot(float(scene.angle[body])).T + scene.position[body]
        direction = float(scene.angle[body] + scene.thruster_angle[k])
        tri = px(np.array([[-0.05, -0.06], [0.16, 0.0], [-0.05, 0.06]]) @ _rot(direction).T + anchor)
        binding = int(np.clip(scene.thruster_binding[k], 0, 1))
        used_thruster.add(binding)
        ops.append(("polygon", (tri,), {"fill": THRUSTER_COLOURS[binding], "outline": OUTLINE, "width": outline},
                    tri))
    return ops


def used_bindings(scene: Scene) -> tuple[set[int], set[int]]:
    """(motor bindings, thruster bindings) the scene's active motors and thrusters listen to: the level's controls."""
    motors = scene.joint_active & ~scene.joint_fixed & scene.motor_on
    motor = {int(np.clip(b, 0, 3)) for b in scene.motor_binding[motors]}
    thruster = {int(np.clip(b, 0, 1)) for b in scene.thruster_binding[scene.thruster_active]}
    return motor, thruster
