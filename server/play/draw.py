"""The human-facing renderer: numpy + Pillow, fast and crisp (not the JAX observation renderer).

    view = View(width, height)                 # the canvas size; the 5 m x 5 m world is letterboxed into it
    rgb = draw_frame(scene_of(level), view, overlay=editor.overlay(), hud="PLAY  step 12  0.40 s")
    x, y = view.to_world(u, v)                 # viser screen_pos (0..1, top-left origin) -> world metres

Shapes are drawn at 2x and reduced to 1x by Pillow's box filter, which anti-aliases every edge at a
fraction of the cost of per-pixel coverage; text is drawn after the reduction (it is anti-aliased already).
Colours follow kinetix.render so the editor, thumbnails and observations look alike.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
from PIL import Image, ImageDraw, ImageFont

WORLD = (0.0, 0.0, 5.0, 5.0)  # the visible world box x0, y0, x1, y1 (metres)
SUPERSAMPLE = 2

BACKGROUND = (250, 250, 250)
LETTERBOX = (226, 228, 232)
ROLE = [(160, 160, 160), (0, 204, 0), (0, 102, 204), (255, 102, 102)]  # none, green, blue, red
FIXED_ROLE = [(80, 80, 80), (0, 102, 0), (0, 51, 102), (128, 51, 51)]  # static bodies darker
OUTLINE = (20, 20, 20)
TEXT = (30, 30, 30)
MOTOR_COLOURS = [(255, 200, 0), (230, 0, 230), (0, 200, 210), (255, 120, 0)]  # motor bindings 0-3
THRUSTER_COLOURS = [(255, 69, 0), (148, 0, 211)]  # thruster bindings 0-1
JOINT_OFF = (255, 255, 255)
WELD = (100, 100, 100)
# The keys of motor binding i: (turns its wheel clockwise, anticlockwise) as server.play.steps maps them. Arrow keys are
# drawn as small arrows (Pillow's bundled font has no arrow glyphs); the characters name them in legend_text.
MOTOR_KEYS = [("→", "←"), ("↓", "↑"), ("S", "W"), ("D", "A")]
THRUSTER_KEYS = ["1", "2"]
PREVIEW = (255, 140, 0)
SELECTION = (0, 150, 255)
GUIDE = (255, 0, 160)
# The editor's messages ("no polygon left: ..."): dark red on a white box, readable over any part of the level (red
# on the dark floor was not), centred at the bottom, at least MESSAGE_CLEAR pixels from the left and right edges:
# viser draws its axes gizmo in the canvas's bottom-left corner (about 60 x 60 pixels).
MESSAGE_INK = (150, 0, 0)
MESSAGE_FILL = (255, 255, 255)
MESSAGE_CLEAR = 80
MESSAGE_SIZE = 13


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


@functools.lru_cache(maxsize=4)
def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # very old Pillow without the bundled scalable font
        return ImageFont.load_default()


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


def draw_frame(scene: Scene | None, view: View, *, overlay=None, hud: str = "", banner: str = "",
               legend: bool = True, message: str | None = None) -> np.ndarray:
    """An (height, width, 3) uint8 RGB frame of the scene with the editor overlay, a HUD line and a banner.

    Static bodies are drawn once per view into a cached layer; per frame only the box around the moving
    bodies, joints, thrusters and overlay is drawn at 2x, reduced and pasted, which keeps a frame near 1-2 ms.
    The frame itself is a numpy array: a Pillow RGB image stores 4 bytes a pixel, so copying the whole frame
    through Pillow and back cost more than drawing it; only the patch and the rows with text go through Pillow.
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
    if overlay is not None:
        ops += _overlay_ops(overlay, px, s)
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
    message = message or getattr(overlay, "message", None)
    items = _legend(used_motor, used_thruster) if legend else []
    if banner or message:  # text anywhere: draw on the whole frame (edit frames and end banners only)
        rows = (0, view.height)
    elif hud or items:  # the HUD line and the legend below it
        oy = int(view.origin[1])
        rows = (oy, min(view.height, oy + TEXT_TOP + LEGEND_ROW * len(items) + 2))
    else:
        return frame
    strip = Image.fromarray(frame[rows[0]:rows[1]])
    _draw_text(strip, view, hud=hud, banner=banner, message=message, legend=items, top=rows[0])
    frame[rows[0]:rows[1]] = np.asarray(strip)
    return frame


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


def _legend(motors: set[int], thrusters: set[int]) -> list[tuple[list[tuple[str, str]], tuple[int, int, int]]]:
    """Legend rows (segments, binding colour); a segment is ("key", key name) or ("text", words). Keys are named by
    their effect: "→ motor 0 clockwise  ← anticlockwise"."""
    rows = []
    for b in sorted(motors):
        clockwise, anticlockwise = MOTOR_KEYS[b]
        rows.append(([("key", clockwise), ("text", f"motor {b} clockwise"), ("key", anticlockwise),
                      ("text", "anticlockwise")], MOTOR_COLOURS[b]))
    return rows + [([("key", THRUSTER_KEYS[b]), ("text", f"thruster {b} fires")], THRUSTER_COLOURS[b])
                   for b in sorted(thrusters)]


def legend_text(motors: set[int], thrusters: set[int]) -> list[str]:
    """The legend's rows as plain text, e.g. ["→ motor 0 clockwise  ← anticlockwise", "1 thruster 0 fires"]."""
    return ["  ".join(f"{name} {words}" for (_, name), (_, words) in zip(segments[::2], segments[1::2], strict=True))
            for segments, _ in _legend(motors, thrusters)]


def _overlay_ops(overlay, px, s: float) -> list:
    width = max(2, round(s * 0.012))
    ops = []
    for x0, y0, x1, y1 in overlay.guides or ():
        pts = px([(x0, y0), (x1, y1)])
        ops.append(("line", (pts,), {"fill": GUIDE, "width": max(1, width // 2)}, pts))
    for item in overlay.selection or ():
        ops += _item_ops(item, px, s, SELECTION, width + 1)
    for item in overlay.preview or ():
        ops += _item_ops(item, px, s, PREVIEW, width)
    if overlay.snap_point is not None:
        cx, cy = px([overlay.snap_point])[0]
        r = 0.05 * s
        box = [(cx - r, cy - r), (cx + r, cy + r)]
        ops.append(("ellipse", (box,), {"outline": GUIDE, "width": width}, box))
    return ops


def _item_ops(item: dict, px, s: float, colour, width: int) -> list:
    kind = item.get("kind")
    if kind == "circle":
        cx, cy = px([item["center"]])[0]
        r = float(item["radius"]) * s
        box = [(cx - r, cy - r), (cx + r, cy + r)]
        return [("ellipse", (box,), {"outline": colour, "width": width}, box)]
    if kind == "polygon" and len(item["points"]) >= 2:
        pts = px(item["points"])
        pts = pts + [pts[0]]
        return [("line", (pts,), {"fill": colour, "width": width, "joint": "curve"}, pts)]
    if kind in ("segment", "arrow"):
        a, b = px([item["a"], item["b"]])
        ops = [("line", ([a, b],), {"fill": colour, "width": width}, [a, b])]
        if kind == "arrow":
            ang = math.atan2(b[1] - a[1], b[0] - a[0])
            head = 0.08 * s
            for side in (2.6, -2.6):
                tip = (b[0] + head * math.cos(ang + side), b[1] + head * math.sin(ang + side))
                ops.append(("line", ([b, tip],), {"fill": colour, "width": width}, [b, tip]))
        return ops
    if kind == "point":
        cx, cy = px([item["at"]])[0]
        r = 0.04 * s
        box = [(cx - r, cy - r), (cx + r, cy + r)]
        return [("ellipse", (box,), {"fill": colour}, box)]
    return []


TEXT_TOP = 22  # pixels from the world box's top to the first legend row (the HUD line is above it)
LEGEND_ROW = 16


def _draw_text(image: Image.Image, view: View, *, hud: str, banner: str, message: str | None, legend: list,
               top: int = 0) -> None:
    """Text in view coordinates, on an image whose first row is the view's row `top`."""
    draw = ImageDraw.Draw(image)
    ox, oy = view.origin
    oy -= top
    if hud:
        _hud_text(image, (ox + 6, oy + 4), hud)
    y = oy + TEXT_TOP
    for segments, colour in legend:
        draw.rectangle([ox + 6, y + 2, ox + 16, y + 12], fill=colour, outline=OUTLINE)
        x = ox + 20
        for kind, text in segments:
            if kind == "key":
                x += _key_cap(draw, image, x, y, text) + 4
            else:
                x += _text(image, (x, y), text, TEXT, 13) + 10
        y += LEGEND_ROW
    if message:
        _message_box(draw, image, view, message, top)
    if banner:
        big = _font(22)
        lines = banner.split("\n")
        h = 28 * len(lines) + 16
        box_top = view.height / 2 - h / 2 - top
        draw.rectangle([0, box_top, view.width, box_top + h], fill=(255, 255, 255), outline=OUTLINE)
        for n, line in enumerate(lines):
            w = draw.textlength(line, font=big)
            _text(image, (view.width / 2 - w / 2, box_top + 8 + 28 * n), line, (20, 20, 20), 22)


def message_lines(message: str, width: float) -> list[str]:
    """`message` broken at spaces into lines of at most `width` pixels (a longer word gets a line of its own)."""
    font = _font(MESSAGE_SIZE)
    lines: list[str] = []
    for paragraph in message.split("\n"):
        line = ""
        for word in paragraph.split(" "):
            candidate = f"{line} {word}" if line else word
            if line and font.getlength(candidate) > width:
                lines.append(line)
                line = word
            else:
                line = candidate
        lines.append(line)
    return lines


def message_box(view: View, message: str) -> tuple[list[str], tuple[int, int, int, int]]:
    """The lines of an editor message and the box (left, top, right, bottom, in view pixels) it is drawn in."""
    lines = message_lines(message, max(80, view.width - 2 * MESSAGE_CLEAR - 16))
    font = _font(MESSAGE_SIZE)
    text_width = max(font.getlength(line) for line in lines)
    row = MESSAGE_SIZE + 5
    width, height = math.ceil(text_width) + 16, row * len(lines) + 10
    left = max(0, (view.width - width) // 2)
    bottom = view.height - 12
    return lines, (left, bottom - height, left + width, bottom)


def _message_box(draw: ImageDraw.ImageDraw, image: Image.Image, view: View, message: str, top: int) -> None:
    lines, (left, box_top, right, bottom) = message_box(view, message)
    draw.rounded_rectangle([left, box_top - top, right, bottom - top], radius=4, fill=MESSAGE_FILL,
                           outline=MESSAGE_INK)
    for n, line in enumerate(lines):
        _text(image, (left + 8, box_top - top + 5 + (MESSAGE_SIZE + 5) * n), line, MESSAGE_INK, MESSAGE_SIZE)


_ARROWS = {"→": 0.0, "↑": 90.0, "←": 180.0, "↓": 270.0}  # key name -> direction the drawn arrow points (degrees)
KEY_CAP = 13  # pixels: the side of a key cap in the legend


def _key_cap(draw: ImageDraw.ImageDraw, image: Image.Image, x: float, y: float, name: str) -> int:
    """A key cap at (x, y): a small box with an arrow or the key's letter; returns its width in pixels."""
    x, y = int(x), int(y)
    width = KEY_CAP if name in _ARROWS else max(KEY_CAP, math.ceil(_font(12).getlength(name)) + 5)
    draw.rounded_rectangle([x, y, x + width, y + KEY_CAP], radius=3, fill=(255, 255, 255), outline=OUTLINE)
    if name in _ARROWS:
        angle = math.radians(_ARROWS[name])
        c, s = math.cos(angle), -math.sin(angle)  # screen y grows downwards
        cx, cy = x + KEY_CAP / 2, y + KEY_CAP / 2
        at = lambda u, v: (cx + u * c - v * s, cy + u * s + v * c)  # noqa: E731  (arrow frame -> pixels)
        draw.line([at(-4, 0), at(1, 0)], fill=TEXT, width=2)
        draw.polygon([at(4.5, 0), at(0, -3.5), at(0, 3.5)], fill=TEXT)
    else:
        _text(image, (x + 3, y), name, TEXT, 12)
    return width


HUD_GAP = 12  # pixels between the HUD's fields


def _hud_text(image: Image.Image, xy: tuple[float, float], hud: str) -> None:
    """The HUD line, field by field ("PLAY", "step 12", "0.40 s", held keys are separated by two spaces): most
    fields repeat from frame to frame, so their cached masks are reused and only the changing numbers are
    rendered."""
    x, y = xy
    for field in hud.split("  "):
        if field:
            x = int(x) + _text(image, (x, y), field, TEXT, 13) + HUD_GAP


@functools.lru_cache(maxsize=512)
def _text_mask(text: str, size: int, fx: float, fy: float) -> tuple[Image.Image, int, int]:
    """(coverage mask, x, y of the pen in it) of `text` drawn with its pen at fraction (fx, fy) of a pixel.

    Drawn by Pillow itself on a black "L" image in white, so the mask is exactly the coverage ImageDraw.text
    blends with; pasting the ink through it gives the same pixels as drawing the text there (tested). FreeType
    renders a line in 0.1-0.2 ms, and the legend and most of the HUD repeat every frame.
    """
    font = _font(size)
    core, (dx, dy) = font.getmask2(text, "L", start=(fx, fy))
    px, py = max(0, -dx), max(0, -dy)  # the pen in the mask, so no glyph starts left of or above it
    w, h = core.size
    mask = Image.new("L", (max(1, px + dx + w), max(1, py + dy + h)), 0)
    ImageDraw.Draw(mask).text((px + fx, py + fy), text, fill=255, font=font)
    return mask, px, py


def _text(image: Image.Image, xy: tuple[float, float], text: str, fill, size: int) -> int:
    """ImageDraw.text(xy, text, fill, font=_font(size)), through a cached mask; returns the text's width in pixels."""
    x, y = xy
    if x < 0 or y < 0:  # ImageDraw splits negative positions differently (toward zero); rare, so not cached
        ImageDraw.Draw(image).text(xy, text, fill=fill, font=_font(size))
        return math.ceil(_font(size).getlength(text))
    ix, iy = int(x), int(y)
    mask, px, py = _text_mask(text, size, x - ix, y - iy)
    image.paste(fill, (ix - px, iy - py), mask)
    return mask.width - px


def encode_jpeg(frame: np.ndarray, quality: int = 85) -> bytes:
    """JPEG bytes of an RGB frame (Pillow; used by tests and the benchmark to measure the wire cost)."""
    import io

    out = io.BytesIO()
    Image.fromarray(frame).save(out, format="JPEG", quality=quality)
    return out.getvalue()
