"""Recordings of plays as MCAP files: write (`Recorder`), read (`read_recording`), replay exactly (`verify`,
`replay_states`, `replay_frames`) and export demonstrations (kinetix.recording.demos).

    with Recorder("play.mcap", level_file, metadata={"player": "human", "name": "ada", "seed": 0}) as rec:
        state, reward, terminated, truncated, info = step(state, action, params)   # step_function(config)
        rec.add_step(action, reward, terminated, truncated, state)
        if rec.wants_frame():
            rec.add_frame(jpeg_bytes)
    recording = read_recording("play.mcap")          # or bytes (an upload)
    assert verify(recording).ok

The file layout is described in kinetix.recording.schema.
"""

from kinetix.recording.errors import RecordingError
from kinetix.recording.reader import Recording, read_recording
from kinetix.recording.replay import (
    ReplayCheck,
    batched_step_function,
    make_env,
    recorded_level,
    replay_frames,
    replay_states,
    step_function,
    verify,
)
from kinetix.recording.writer import Recorder, remove_partial_files

__all__ = ["Recorder", "Recording", "RecordingError", "ReplayCheck", "batched_step_function", "make_env",
           "read_recording", "replay_frames", "recorded_level", "remove_partial_files", "replay_states",
           "step_function", "verify"]
