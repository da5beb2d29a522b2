"""In real headless Chromium with the real editor: draw, join, play; undo and redo; export and re-import."""

from __future__ import annotations

import io
import time

import numpy as np
import pytest
from PIL import Image

from tests.e2e.conftest import LEVELS, Tab, canvas_box
from tests.server.conftest import running_app, wait_until

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


@pytest.fixture(scope="module")
def app():
    with running_app(warm_sizes=("m",)) as app:
        yield app


@pytest.fixture(scope="module")
def car_app():
    with running_app(warm_sizes=(), level=str(LEVELS / "car_right.json")) as app:
        yield app


def _wait(predicate, timeout=20.0):
    wait_until(predicate, timeout)


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)


def test_draw_rectangle_and_circle_join_with_a_motor_and_play(browser, app):
    tab = Tab(browser, app, 1280, 800)  # the panel is docked on the right, beside the canvas
    try:
        page, session = tab.page, tab.session
        editor = session.editor
        bodies = len(editor.spec.bodies)
        page.get_by_role("button", name="Rect", exact=True).click()
        _wait(lambda: editor.tool == "rectangle")
        tab.drag((1.0, 1.0), (2.0, 1.4))
        _wait(lambda: len(editor.spec.bodies) == bodies + 1)
        page.get_by_role("button", name="Circle", exact=True).click()
        _wait(lambda: editor.tool == "circle")
        tab.drag((2.0, 1.2), (2.3, 1.2))
        _wait(lambda: len(editor.spec.bodies) == bodies + 2)
        assert {b.shape for b in editor.spec.bodies[bodies:]} == {"polygon", "circle"}
        page.get_by_role("button", name="Hinge", exact=True).click()
        _wait(lambda: editor.tool == "revolute")
        page.mouse.click(*tab.xy(1.9, 1.2))  # inside both the rectangle and the circle
        _wait(lambda: len(editor.spec.joints) == 1)
        page.get_by_text("Motor on", exact=True).click()
        _wait(lambda: editor.spec.joints[0].motor_on)
        assert editor.spec.joints[0].motor_binding == 0  # Left/Right

        page.mouse.click(*tab.xy(3.0, 4.0))  # focus the canvas (an empty spot; the hinge tool just says so)
        page.keyboard.press("Space")
        _wait(lambda: session.mode == "play")
        time.sleep(1.5)  # the assembly falls and settles on the floor
        still = _pixels(tab.canvas_png(500, 260, 800))
        page.keyboard.down("ArrowRight")
        _wait(lambda: "ArrowRight" in session.held)
        assert session.keys_action()[0] != 0  # motor binding 0 driven (the sign is the level's clockwise turn)
        # The car moves on the canvas; on a loaded 2-core machine the browser can lag, so look for up to 20 s.
        deadline = time.monotonic() + 20
        while np.abs(_pixels(tab.canvas_png(500, 260, 800)) - still).sum() <= 10_000:
            assert time.monotonic() < deadline, "the frames did not change while ArrowRight was held"
            time.sleep(0.5)
        page.keyboard.up("ArrowRight")
        _wait(lambda: not session.held)
        assert not session.keys_action().any()  # released: the motor binding is no longer driven
        page.keyboard.press("Space")
        _wait(lambda: session.mode == "edit")
        assert len(editor.spec.bodies) == bodies + 2 and editor.spec.bodies[-1].position == pytest.approx((2.0, 1.2))
        tab.assert_local_only()
    finally:
        tab.close()


def test_undo_and_redo(browser, car_app):
    tab = Tab(browser, car_app)
    try:
        editor = tab.session.editor
        bodies = len(editor.spec.bodies)
        body = next(b for b in editor.spec.bodies if not b.fixed)  # a moving body (the walls are fixed)
        tab.page.mouse.click(*tab.xy(*body.position))
        _wait(lambda: editor.selection)
        tab.page.keyboard.press("Delete")
        _wait(lambda: len(editor.spec.bodies) < bodies)
        deleted = len(editor.spec.bodies)
        tab.page.keyboard.press("Control+z")
        _wait(lambda: len(editor.spec.bodies) == bodies)
        tab.page.keyboard.press("Control+Shift+z")
        _wait(lambda: len(editor.spec.bodies) == deleted)
        tab.page.get_by_role("button", name="Undo", exact=True).click()  # the panel's button does the same
        _wait(lambda: len(editor.spec.bodies) == bodies)
        tab.assert_local_only()
    finally:
        tab.close()


def test_export_and_reimport_give_the_same_level(browser, car_app, tmp_path):
    tab = Tab(browser, car_app)
    try:
        editor, page = tab.session.editor, tab.page
        original = editor.export("ours")
        with page.expect_download() as download:
            page.get_by_role("button", name="Download (our format)", exact=True).click()
        saved = tmp_path / "exported.json"
        download.value.save_as(saved)
        assert saved.read_text() == original
        page.get_by_role("button", name="New level", exact=True).click()
        _wait(lambda: editor.export("ours") != original)
        with page.expect_file_chooser() as chooser:
            page.get_by_role("button", name="Upload level", exact=True).click()
        chooser.value.set_files(str(saved))
        _wait(lambda: editor.export("ours") == original)
        tab.assert_local_only()
    finally:
        tab.close()


def _message_ink(png: bytes) -> np.ndarray:
    """Mask of the editor message's red ink in a screenshot, dark or bright red and blended into any background by
    anti-aliasing (not the red role's pink, which is brighter)."""
    rgb = _pixels(png)
    return (rgb[..., 0] - rgb[..., 1:].max(axis=2) > 60) & (rgb[..., 0] < 235)


def test_a_size_refusal_message_is_readable_clear_of_the_gizmo_and_goes_with_move_to_size(browser, app):
    tab = Tab(browser, app, 1280, 800)
    try:
        page, editor = tab.page, tab.session.editor
        box = canvas_box(page)

        def shot() -> bytes:
            return tab.canvas_png(round(box["y"]), round(box["height"]), round(box["x"] + box["width"]))

        page.get_by_role("button", name="Rect", exact=True).click()
        _wait(lambda: editor.tool == "rectangle")
        page.wait_for_timeout(500)
        gizmo = _message_ink(shot())  # red before any message: viser's axes gizmo (its x axis)

        def ink(png: bytes) -> np.ndarray:
            return _message_ink(png) & ~gizmo

        free = editor.limits()["polygons"][1] - editor.limits()["polygons"][0]
        for n in range(free + 1):  # the last one is refused: the size class is full
            tab.drag((0.8 + 1.1 * n, 1.0), (1.4 + 1.1 * n, 1.4))
        _wait(lambda: "no polygon left" in (editor.message or ""))
        _wait(lambda: ink(shot()).sum() > 50)
        png = shot()
        ys, xs = np.nonzero(ink(png))
        height = gizmo.shape[0]
        # viser's axes gizmo takes the canvas's bottom-left corner (about 60 x 60 pixels): the message keeps clear.
        assert xs.min() > 70 or ys.max() < height - 70, "the message is under viser's axes gizmo"
        around = _pixels(png)[ys.min():ys.max() + 1, xs.min():xs.max() + 1]
        paper = around[~ink(png)[ys.min():ys.max() + 1, xs.min():xs.max() + 1]].mean(axis=1)
        assert np.median(paper) > 200, "the message is drawn on a light background, not on the dark floor"

        page.get_by_role("button", name="Move to size l", exact=True).click()
        _wait(lambda: editor.size.name == "l" and editor.limits()["polygons"][0] == 4 + free + 1)
        # The refusal's cause is gone: so is its message, on the canvas too (it stayed until a reload).
        _wait(lambda: ink(shot()).sum() == 0)
        tab.drag((3.0, 3.0), (3.5, 3.5))  # a later edit, then Esc: still no message
        _wait(lambda: editor.limits()["polygons"][0] == 4 + free + 2)
        page.keyboard.press("Escape")
        page.wait_for_timeout(500)
        assert ink(shot()).sum() == 0
        tab.assert_local_only()
    finally:
        tab.close()


def test_a_hinge_snaps_only_from_a_few_pixels_and_no_guide_stays_after_it(browser, app):
    """A hinge clicked 10 pixels below the top of a circle stays where it was clicked (it was moved to the top:
    the snap radius was 0.08 m, 11 pixels here); one clicked 2 pixels from the top snaps to it, shows the ring of
    what it snapped to, and no guide line stays on the canvas after the edit."""
    from server.editor import selection as sel

    tab = Tab(browser, app, 1280, 800)
    try:
        page, editor = tab.page, tab.session.editor
        box = canvas_box(page)
        page.get_by_role("button", name="New level", exact=True).click()
        _wait(lambda: len(editor.spec.bodies) == 4)
        page.get_by_role("button", name="Rect", exact=True).click()
        _wait(lambda: editor.tool == "rectangle")
        tab.drag((1.5, 0.9), (2.5, 1.6))
        page.get_by_role("button", name="Circle", exact=True).click()
        _wait(lambda: editor.tool == "circle" and len(editor.spec.bodies) == 5)
        tab.drag((2.0, 1.2), (2.2, 1.2))
        _wait(lambda: len(editor.spec.bodies) == 6)
        circle = editor.spec.bodies[5]
        top = (circle.position[0], circle.position[1] + circle.radius)
        pixels_per_metre = tab.xy(1.0, 0.0)[0] - tab.xy(0.0, 0.0)[0]
        editor.grid = 0.0  # the grid off: only the features snap
        page.get_by_role("button", name="Hinge", exact=True).click()
        _wait(lambda: editor.tool == "revolute")

        page.mouse.click(*tab.xy(top[0], top[1] - 10 / pixels_per_metre))  # 10 pixels below the top
        _wait(lambda: len(editor.spec.joints) == 1)
        at = sel.joint_point(editor.spec, editor.spec.joints[0])
        assert abs(at[1] - top[1]) * pixels_per_metre > 7, f"snapped from 10 pixels away to {at} (top {top})"

        page.keyboard.press("Control+z")
        _wait(lambda: not editor.spec.joints)
        page.mouse.click(*tab.xy(top[0] + 1 / pixels_per_metre, top[1] - 2 / pixels_per_metre))  # 2 pixels off
        _wait(lambda: len(editor.spec.joints) == 1)
        at = sel.joint_point(editor.spec, editor.spec.joints[0])
        assert at == pytest.approx(top, abs=1e-6), "a click right by the circle's top snaps to it"
        page.wait_for_timeout(700)
        shot = _pixels(tab.canvas_png(round(box["y"]), round(box["height"]), round(box["x"] + box["width"])))
        guide = (np.abs(shot - np.array([255, 0, 160])).max(axis=2) < 60)
        ys, xs = np.nonzero(guide)
        assert len(xs), "the ring of the point it snapped to is shown"
        ring = 0.05 * pixels_per_metre + 4  # the ring's radius (server.play.draw) and its line
        cx, cy = tab.xy(*top)
        assert (np.hypot(xs + 0.5 - cx, ys + 0.5 - (cy - box["y"])) <= ring + 3).all(), \
            "a snap guide line is still on the canvas after the edit"
        tab.assert_local_only()
    finally:
        tab.close()
