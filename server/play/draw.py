"""The browser's frames: kinetix.draw's level drawing with the editor overlay, the HUD, the legend and banners.

    view = View(width, height)                 # the canvas size; the 5 m x 5 m world is letterboxed into it
    rgb = draw_frame(scene_of(level), view, overlay=editor.overlay(), hud="PLAY  step 12  0.40 s")
    x, y = view.to_world(u, v)                 # viser screen_pos (0..1, top-left origin) -> world metres

The shapes are drawn at 2x and reduced by kinetix.draw; text is drawn after the reduction (it is anti-aliased
already).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from PIL import Image, ImageDraw, ImageFont

# The level drawing lives in kinetix (kinetix.gym renders with it too); its names stay importable from here.
from kinetix.draw import (  # noqa: F401
    BACKGROUND,
    FIXED_ROLE,
    JOINT_OFF,
    LETTERBOX,
    MOTOR_COLOURS,
    OUTLINE,
    ROLE,
    SUPERSAMPLE,
    THRUSTER_COLOURS,
    WELD,
    WORLD,
    Scene,
    View,
    draw_scene,
    scene_of,
    used_bindings,
)

TEXT = (30, 30, 30)
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


@functools.lru_cache(maxsize=4)
def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # very old Pillow without the bundled scalable font
        return ImageFont.load_default()


def draw_frame(scene: Scene | None, view: View, *, overlay=None, hud: str = "", banner: str = "",
               legend: bool = True, message: str | None = None) -> np.ndarray:
    """An (height, width, 3) uint8 RGB frame of the scene with the editor overlay, a HUD line and a banner.

    The scene and overlay come from kinetix.draw.draw_scene; only the rows with text go through Pillow again.
    """
    extra = None if overlay is None else functools.partial(_overlay_ops, overlay)
    frame, used_motor, used_thruster = draw_scene(scene, view, extra)
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
