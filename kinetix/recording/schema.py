"""What a kinetix recording holds: the MCAP profile, topics, schemas and the small encoders shared by writer and reader.

Layout (one MCAP file, zstd chunks, profile "kinetix-recording"):
  /level        once   our level format (JSON text of kinetix.levels.dumps), readable by people and Foxglove
  /level/exact  once   attachment "level.npz": every array of the initial Level, so replay starts bitwise equal
  /step         per env step: {"step", "action", "reward", "terminated", "truncated"[, "batch"]}; `action` is the exact
                array (list of ints, or floats of float32 values: a float32 widened to a JSON double round-trips
                exactly); `batch` (only when not 1): the step ran in a vmapped batch of that many plays
  /state        per env step: the dynamic state after the step of each active body: position, rotation, velocity,
                angular velocity, as JSON numbers (exact float32, same reason)
  /camera       rendered frames, at most 10 Hz, foxglove.CompressedImage (jsonschema, JPEG, base64 data)
  metadata "kinetix.recording" (who played, level id, seed, versions, env) and "kinetix.summary" (written at close)
"""

from __future__ import annotations

import json

PROFILE = "kinetix-recording"
FORMAT_VERSION = "1"
TOPIC_LEVEL = "/level"
TOPIC_STEP = "/step"
TOPIC_STATE = "/state"
TOPIC_CAMERA = "/camera"
LEVEL_ATTACHMENT = "level.npz"
METADATA = "kinetix.recording"
SUMMARY = "kinetix.summary"
FRAME_ID = "kinetix_world"
MAX_FRAME_HZ = 10.0

COMPRESSED_IMAGE = {
    "title": "foxglove.CompressedImage",
    "description": "A compressed image",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "title": "time",
            "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0,
                                                                                "maximum": 999999999}},
        },
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
}

_FLOATS = {"type": "array", "items": {"type": "number"}}
STEP_SCHEMA = {
    "title": "kinetix.Step",
    "type": "object",
    "properties": {
        "step": {"type": "integer"},
        "action": {"type": "array", "items": {"type": "number"}},
        "reward": {"type": "number"},
        "terminated": {"type": "boolean"},
        "truncated": {"type": "boolean"},
        "batch": {"type": "integer", "description": "stepped by a vmapped transition over this many plays "
                                                    "(absent: 1, a single step)"},
    },
}
STATE_SCHEMA = {
    "title": "kinetix.BodyStates",
    "type": "object",
    "properties": {
        "step": {"type": "integer"},
        "bodies": {"type": "array", "items": {"type": "integer"}},
        "position": {"type": "array", "items": _FLOATS},
        "rotation": _FLOATS,
        "velocity": {"type": "array", "items": _FLOATS},
        "angular_velocity": _FLOATS,
    },
}
LEVEL_SCHEMA = {"title": "kinetix.Level", "type": "object", "description": "a level in the kinetix-playground format"}


def schema_bytes(schema: dict) -> bytes:
    return json.dumps(schema, separators=(",", ":")).encode()


def dumps(message: dict) -> bytes:
    return json.dumps(message, separators=(",", ":"), allow_nan=True).encode()
