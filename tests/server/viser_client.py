"""A headless client speaking viser 1.1.1's websocket protocol, for protocol-level tests and benchmarks.

Windows from the server: [u64 raw size][u64 compressed size][zstd(msgpack{messages, timestampSec,
binaryBufferLengths})][8-byte aligned raw buffers]; numpy/bytes payloads appear in messages as
{"__binary_index": i, ...} placeholders. Messages to the server are plain msgpack dicts with a "type" key.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import msgspec
import viser
import websockets.sync.client
import zstandard


def _resolve(value, buffers: list[bytes]):
    if isinstance(value, dict):
        if "__binary_index" in value:
            return buffers[value["__binary_index"]]
        return {k: _resolve(v, buffers) for k, v in value.items()}
    if isinstance(value, list):
        return [_resolve(v, buffers) for v in value]
    return value


def decode_window(data: bytes) -> list[dict]:
    raw_size = int.from_bytes(data[0:8], "little")
    comp_size = int.from_bytes(data[8:16], "little")
    inner = msgspec.msgpack.decode(zstandard.ZstdDecompressor().decompress(data[16:16 + comp_size],
                                                                           max_output_size=raw_size))
    offset, buffers = 16 + comp_size, []
    for length in inner.get("binaryBufferLengths", ()):
        offset += (8 - offset % 8) % 8
        buffers.append(bytes(data[offset:offset + length]))
        offset += length
    return [_resolve(m, buffers) for m in inner["messages"]]


def is_frame(message: dict) -> bool:
    """A background image that carries pixels (a level frame)."""
    return message["type"] == "BackgroundImageMessage" and message.get("rgb_data") is not None


class ViserTestClient:
    """Connects, announces a camera of `width` x `height` and records every message the server sends."""

    def __init__(self, port: int, width: int = 640, height: int = 480, host: str = "127.0.0.1",
                 token: str | None = None, path: str = ""):
        """`token`: the app's relay_token, for a client that connects to viser's internal port straight
        (server.web.relay: that port refuses anyone without it); a client of the user's port needs none."""
        self.width, self.height = width, height
        self.messages: list[dict] = []
        self._cond = threading.Condition()
        self.ws = websockets.sync.client.connect(f"ws://{host}:{port}{path}",
                                                 subprotocols=[f"viser-v{viser.__version__}"],
                                                 max_size=None, open_timeout=10,
                                                 additional_headers={"X-Kinetix-Relay": token} if token else None)
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()
        self.send_camera(width, height)

    def _receive(self) -> None:
        try:
            for data in self.ws:
                if isinstance(data, bytes):
                    messages = decode_window(data)
                    with self._cond:
                        self.messages.extend(messages)
                        self._cond.notify_all()
        except Exception:  # closed
            pass

    def send(self, message_type: str, **fields) -> None:
        self.ws.send(msgspec.msgpack.encode({"type": message_type, **fields}))

    def send_camera(self, width: int, height: int) -> None:
        self.width, self.height = width, height
        self.send("ViewerCameraMessage", wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.0, 0.0, -5.0), fov=1.0, near=0.01,
                  far=1000.0, image_height=height, image_width=width, look_at=(0.0, 0.0, 0.0),
                  up_direction=(0.0, -1.0, 0.0))

    def close(self) -> None:
        self.ws.close()
        self._thread.join(timeout=5)

    # ------------------------------------------------------------------ waiting and reading

    def wait_for(self, predicate: Callable[[dict], bool], timeout: float = 10.0, start: int = 0) -> dict:
        """The first message from index `start` on matching `predicate`, waiting up to `timeout` seconds."""
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                for m in self.messages[start:]:
                    if predicate(m):
                        return m
                left = deadline - time.monotonic()
                if left <= 0:
                    raise TimeoutError("no matching message from the server")
                self._cond.wait(left)

    def count(self) -> int:
        with self._cond:
            return len(self.messages)

    def matching(self, predicate: Callable[[dict], bool]) -> list[dict]:
        """Every message received so far that matches `predicate`, in arrival order."""
        with self._cond:
            return [m for m in self.messages if predicate(m)]

    def kinds(self) -> list[str]:
        """Each message's type in arrival order, "frame" for a level frame (is_frame)."""
        with self._cond:
            return ["frame" if is_frame(m) else m["type"] for m in self.messages]

    def frames(self, start: int = 0) -> list[bytes]:
        with self._cond:
            return [m["rgb_data"] for m in self.messages[start:] if is_frame(m)]

    def wait_frame(self, start: int = 0, timeout: float = 10.0) -> bytes:
        return self.wait_for(is_frame, timeout, start)["rgb_data"]

    def gui(self) -> dict[str, dict]:
        """Current GUI elements by uuid (creation messages with later updates applied)."""
        elements: dict[str, dict] = {}
        with self._cond:
            for m in self.messages:
                if m["type"].startswith("Gui") and "uuid" in m and m["type"] != "GuiUpdateMessage":
                    elements[m["uuid"]] = {"type": m["type"], **m.get("props", {}), "uuid": m["uuid"]}
                elif m["type"] == "GuiUpdateMessage" and m["uuid"] in elements:
                    elements[m["uuid"]].update(m["updates"])
                elif m["type"] == "GuiRemoveMessage":
                    elements.pop(m["uuid"], None)
        return elements

    def find_gui(self, label: str, timeout: float = 10.0) -> dict:
        """The GUI element with this label, waiting for it: a session's panels are built after it is registered,
        so a test that found the session may look before they arrive."""
        deadline = time.monotonic() + timeout
        while True:
            for element in self.gui().values():
                if element.get("label") == label:
                    return element
            if time.monotonic() >= deadline:
                labels = [e.get("label") for e in self.gui().values()]
                raise KeyError(f"no GUI element labelled {label!r}; have {labels}")
            with self._cond:
                self._cond.wait(0.05)

    def html_containing(self, text: str) -> str:
        for element in self.gui().values():
            if element["type"] == "GuiHtmlMessage" and text in element.get("content", ""):
                return element["content"]
        raise KeyError(text)

    # ------------------------------------------------------------------ input

    def click_button(self, label: str) -> None:
        self.send("GuiUpdateMessage", uuid=self.find_gui(label)["uuid"], updates={"value": True})

    def click(self, u: float, v: float, modifier: str | None = None) -> None:
        self.send("ScenePointerMessage", event_type="click", ray_origin=(0.0, 0.0, -5.0), ray_direction=(0.0, 0.0, 1.0),
                  screen_pos=[[u, v]], modifier=modifier)

    def rect_select(self, u0: float, v0: float, u1: float, v1: float) -> None:
        self.send("ScenePointerMessage", event_type="rect-select", ray_origin=None, ray_direction=None,
                  screen_pos=[[u0, v0], [u1, v1]], modifier="shift")

    def drag(self, name: str, points: list[tuple[float, float]], modifier: str | None = None, owner: str = "") -> None:
        """start at points[0], updates through the middle, end at points[-1] (screen positions 0..1).

        `owner` echoes the node's scope: the client id as a string for client-scoped nodes."""
        start = points[0]
        for i, point in enumerate(points):
            phase = "start" if i == 0 else "end" if i == len(points) - 1 else "update"
            self.send("SceneNodeDragMessage", phase=phase, name=name, instance_index=None,
                      start_position=(0.0, 0.0, 0.0), start_screen_pos=start, end_position=(0.0, 0.0, 0.0),
                      end_screen_pos=point, button="left", modifier=modifier, owner=owner)


class KeysSocket:
    """The /keys websocket as keys.js speaks it: hello with the tab's nonce, then down/up events."""

    def __init__(self, port: int, nonce: str, host: str = "127.0.0.1", query: str = "", token: str | None = None,
                 path: str = "", tab: str | None = None):
        import json

        self._json = json
        self.ws = websockets.sync.client.connect(f"ws://{host}:{port}{path}/keys", open_timeout=10)
        self.ws.send(json.dumps({"type": "hello", "nonce": nonce, "query": query, "token": token, "tab": tab}))
        self.reply = json.loads(self.ws.recv(timeout=10))
        self.seq = 0

    def send(self, kind: str, code: str, key: str = "", **mods) -> int:
        self.seq += 1
        self.ws.send(self._json.dumps({"type": kind, "code": code, "key": key or code, "seq": self.seq,
                                       "t": time.time() * 1000, **{m: bool(mods.get(m)) for m in
                                                                    ("ctrl", "shift", "alt", "meta")}}))
        return self.seq

    def down(self, code: str, key: str = "", **mods) -> int:
        return self.send("down", code, key, **mods)

    def up(self, code: str, key: str = "", **mods) -> int:
        return self.send("up", code, key, **mods)

    def close(self) -> None:
        self.ws.close()


def session_nonce(client: ViserTestClient, timeout: float = 10.0) -> str:
    import re

    message = client.wait_for(lambda m: m["type"] == "GuiHtmlMessage" and "kinetix-session" in m["props"]["content"],
                              timeout)
    return re.search(r'data-nonce="([^"]+)"', message["props"]["content"]).group(1)
