"""Frames on the wire: the JPEG background a session pushes, the hidden acknowledgement of the key it answers, and the
preview of a level that a page carries until its session's first frame arrives."""

from __future__ import annotations

import numpy as np

from server.play import draw

MAX_PIXELS = 1280 * 800  # larger canvases are rendered smaller at the same aspect ratio (the browser scales up)
JPEG_QUALITY = 85
# The preview is square, as the world is: the page letterboxes it into its canvas as frames are (static/frames.js).
PREVIEW_PIXELS = 640


def ack_html(seq: int) -> str:
    """The hidden element that acknowledges key `seq` in the batch of the frame it produced (static/frames.js and
    the benchmark read this exact form)."""
    return f'<div id="kinetix-ack" data-seq="{seq}" hidden></div>'


def set_background_jpeg(client, data: bytes, frame: np.ndarray) -> None:
    """Queue an already encoded JPEG as the scene background.

    Pillow encodes a frame about twice as fast as viser's imageio fallback (no OpenCV here), which matters with 8
    sessions at 30 fps. viser 1.1.1 (pinned) has no public call for encoded bytes, so this queues the same message
    set_background_image would, and falls back to the public call if viser's internals ever differ.
    """
    try:
        from viser._messages import BackgroundImageMessage

        queue = client.scene._websock_interface.queue_message
    except (ImportError, AttributeError):
        client.scene.set_background_image(frame, format="jpeg", jpeg_quality=JPEG_QUALITY)
        return
    queue(BackgroundImageMessage(format="jpeg", rgb_data=data, depth_data=None))


def canvas_view(client) -> draw.View:
    """A view at the size of the tab's canvas as the browser reports it, at most MAX_PIXELS (same aspect ratio)."""
    cam = client.camera
    try:
        w, h = int(cam.image_width), int(cam.image_height)
    except Exception:  # the camera is not known yet
        w, h = 512, 512
    w, h = max(w, 64), max(h, 64)
    if w * h > MAX_PIXELS:
        f = (MAX_PIXELS / (w * h)) ** 0.5
        w, h = int(w * f), int(h * f)
    return draw.View(w, h)


def preview_jpeg(level) -> bytes:
    """The level as a tab's first frame shows it (without the HUD line, which names the tab's state), square, as JPEG:
    server.web.http puts it in the page of an address that names the level (?level=, ?draft=), and static/frames.js
    draws it on the canvas the moment viser's canvas exists, about a second before the session's first frame can
    arrive (viser's client starts, connects, and the session is built first; issue 37: the canvas stayed blank)."""
    view = draw.View(PREVIEW_PIXELS, PREVIEW_PIXELS)
    return draw.encode_jpeg(draw.draw_frame(draw.scene_of(level), view), JPEG_QUALITY)
