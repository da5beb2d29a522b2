"""Frames on the wire: the JPEG background a session pushes, the hidden acknowledgement of the key it answers, and the
preview of a level that a page carries until its session's first frame arrives."""

from __future__ import annotations

import time

import numpy as np

from server.play import draw

MAX_PIXELS = 1280 * 800  # larger canvases are rendered smaller at the same aspect ratio (the browser scales up)
JPEG_QUALITY = 85
# The preview is square, as the world is: the page letterboxes it into its canvas as frames are (static/frames.js).
PREVIEW_PIXELS = 640
# How long a new session waits for its first frame to leave viser's buffer before it builds the panel
# (wait_until_sent): a few milliseconds on a quiet server; the bound only matters if the tab never reads.
FIRST_FRAME_WAIT_S = 2.0


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


def wait_until_sent(client, timeout: float) -> bool:
    """Wait until viser has taken every message queued so far for `client` off its buffer and onto the socket, at
    most `timeout` seconds; True if it has.

    Why: viser keeps only the newest background image in a client's buffer. On a loaded server a tab's session can
    queue its first frame, its panel and a second frame before viser's sender for that tab first runs; the first
    frame is then dropped and the second goes out after the panel, so the canvas stays blank while the browser
    builds the panel (a second or more; CI of stop 61). Waiting for the first frame to leave costs a few
    milliseconds on a quiet server. viser 1.1.1 (pinned) has no public call for this: if its internals differ,
    this returns False at once (the old behaviour)."""
    try:
        buffer = client._websock_connection.get_message_buffer()
        last, cursors = buffer.message_counter - 1, buffer.generator_cursors
    except AttributeError:
        return False
    deadline = time.monotonic() + timeout
    while cursors.get(client.client_id, -1) < last:
        if buffer.done or time.monotonic() >= deadline:
            return False
        time.sleep(0.005)
    return True


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
