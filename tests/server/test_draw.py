"""The human-facing renderer: letterboxed mapping, role colours, anti-aliasing, markers and the overlay."""

from __future__ import annotations

import numpy as np
import pytest
from fake_editor import FakeOverlay, falling_win_spec

from kinetix.formats import JointSpec, build
from server.play.draw import ROLE, View, draw_frame, scene_of


def test_view_letterboxes_and_round_trips():
    view = View(800, 600)
    assert view.scale == 120.0 and view.origin == (100.0, 0.0)
    assert view.to_world(0.5, 0.5) == pytest.approx((2.5, 2.5))
    for x, y in [(0.0, 0.0), (5.0, 5.0), (1.25, 3.5)]:
        assert view.to_world(*view.to_screen(x, y)) == pytest.approx((x, y))


@pytest.fixture(scope="module")
def level():
    return build(falling_win_spec(), None).level


def test_bodies_have_role_colours_and_anti_aliased_edges(level):
    view = View(500, 500)
    frame = draw_frame(scene_of(level), view, legend=False)
    assert frame.shape == (500, 500, 3) and frame.dtype == np.uint8
    cx, cy = (round(c) for c in view.to_pixel(2.5, 1.6))
    assert frame[cy + 10, cx].tolist() == list(ROLE[1])  # inside the green ball (below its rotation line)
    assert frame[cy, cx + 5].tolist() != list(ROLE[1])  # the rotation line shows the circle's angle
    # Along a row through the ball there are blended pixels between green and the background.
    row = frame[cy, cx: cx + 40].astype(int)
    blended = [p for p in row if 0 < p[1] < 204 and p.tolist() not in ([20, 20, 20],)]
    assert len({tuple(p) for p in row}) > 3 and blended


def test_the_browser_frame_without_text_is_kinetix_draws_level_frame(level):
    """kinetix.gym's rgb_array frames come from kinetix.draw.level_frame: the browser's frames less the text."""
    from kinetix.draw import level_frame

    view = View(320, 240)
    frame = draw_frame(scene_of(level), view, legend=False)
    assert np.array_equal(frame, level_frame(level, view))
    assert not np.array_equal(draw_frame(scene_of(level), view, hud="PLAY"), frame)


def test_overlay_hud_and_banner_change_the_frame(level):
    view = View(400, 300)
    base = draw_frame(scene_of(level), view)
    overlay = FakeOverlay(preview=[{"kind": "circle", "center": (1.0, 4.0), "radius": 0.5}],
                          guides=[(0.0, 2.0, 5.0, 2.0)], message="polygon is not convex")
    with_overlay = draw_frame(scene_of(level), view, overlay=overlay)
    px, py = (round(c) for c in view.to_pixel(1.0, 4.5))
    assert (with_overlay[py - 2: py + 3, px] != base[py - 2: py + 3, px]).any()
    assert (draw_frame(scene_of(level), view, hud="PLAY step 3") != base).any()
    assert (draw_frame(scene_of(level), view, banner="You won!") != base).any()


def test_motor_joints_get_a_key_legend():
    spec = falling_win_spec()
    spec.bodies[-1].fixed = False
    spec.joints.append(JointSpec(path="j", a=4, b=5, anchor_a=(0.0, -0.2), anchor_b=(0.0, 0.2), motor_on=True,
                                 motor_binding=1))
    level = build(spec, None).level
    view = View(400, 400)
    with_legend = draw_frame(scene_of(level), view)
    without = draw_frame(scene_of(level), view, legend=False)
    assert (with_legend[20:60, :150] != without[20:60, :150]).any()


@pytest.mark.parametrize("size", [(640, 480), (400, 800)])
def test_hud_drawn_on_its_rows_matches_drawing_on_the_whole_frame(level, size):
    """Frames draw the HUD on a strip of rows only (for speed); the pixels must equal drawing on the whole frame."""
    from PIL import Image

    from server.play.draw import _draw_text

    view = View(*size)
    hud = "PLAY  step 120  4.00 s  ArrowRight"
    frame = draw_frame(scene_of(level), view, hud=hud, legend=False)
    whole = Image.fromarray(draw_frame(scene_of(level), view, legend=False))
    _draw_text(whole, view, hud=hud, banner="", message=None, legend=[])
    assert np.array_equal(frame, np.asarray(whole))
    assert not np.array_equal(frame, draw_frame(scene_of(level), view, legend=False)), "the HUD is drawn at all"
    corner = frame[0, 0].copy()
    frame[0, 0] = 255 - corner  # a frame is a fresh array: writing to it must not touch the cached static layer
    assert np.array_equal(draw_frame(scene_of(level), view, hud=hud, legend=False)[0, 0], corner)


def test_cached_text_has_the_pixels_of_pillows_text():
    """Text is pasted through cached coverage masks (server.play.draw._text); on any background and at fractional
    positions it must give exactly the pixels ImageDraw.text gives."""
    from PIL import Image, ImageDraw

    from server.play.draw import _font, _text

    rng = np.random.default_rng(0)
    for i in range(120):
        text = f"step {rng.integers(0, 5000)}  {rng.random() * 80:.2f} s  motor {i % 4}: ←/→ You won!"[: 5 + i % 40]
        size = (13, 22)[i % 2]
        xy = (float(rng.random() * 30 - 4), float(rng.random() * 30 - 6))  # some negative, some off the edge
        base = Image.fromarray(rng.integers(0, 256, (48, 260 if i % 3 else 60, 3), dtype=np.uint8))
        expected = base.copy()
        ImageDraw.Draw(expected).text(xy, text, fill=(30, 30, 30), font=_font(size))
        for _ in range(2):  # the second call comes from the cache
            got = base.copy()
            _text(got, xy, text, (30, 30, 30), size)
            assert np.array_equal(np.asarray(got), np.asarray(expected)), (text, xy, size)


@pytest.mark.parametrize("size", [(640, 480), (300, 300), (1280, 800)])
def test_an_editor_message_is_boxed_at_the_bottom_clear_of_the_axes_gizmo(level, size):
    from server.play.draw import MESSAGE_CLEAR, MESSAGE_FILL, message_box

    view = View(*size)
    text = 'no polygon left: 6 of 6 used in size m; "Move to size l" in the panel makes room'
    lines, (left, top, right, bottom) = message_box(view, text)
    assert " ".join(lines) == text
    assert bottom <= view.height and top >= view.height / 2, "at the bottom of the canvas"
    if view.width >= 400:  # viser's gizmo sits in the bottom-left corner (about 60 x 60 pixels)
        assert left >= MESSAGE_CLEAR - 10 and right <= view.width - MESSAGE_CLEAR + 10
    frame = draw_frame(scene_of(level), view, message=text)
    assert (frame[top + 2, (left + right) // 2] == MESSAGE_FILL).all(), "on a white box"
