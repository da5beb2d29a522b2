"""Recordings: write/read round trip, Foxglove fields, exact replay, bad files, abort and crashes, export-demos."""

from __future__ import annotations

import base64
import io
import json
import os
import signal
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import jax
import numpy as np
import pytest
from mcap.records import Chunk
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

import jax2d
from kinetix.env import EnvConfig, EnvParams, make_env
from kinetix.levels import load_level
from kinetix.recording import Recorder, RecordingError, read_recording, verify
from kinetix.recording.demos import export_demos
from kinetix.recording.play import play_episode

ROOT = Path(__file__).resolve().parents[3]
# s and m sizes only (one compiled step each): joints (unicycle, car_ramp) and thrusters (thrust_hop, octagon_roll)
LEVELS = ["thrust_hop", "unicycle", "car_ramp", "octagon_roll"]
STEPS = 60


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp("recordings")
    paths = {}
    for i, name in enumerate(LEVELS):
        paths[name] = out / f"{name}.mcap"
        play_episode("random", load_level(ROOT / "levels" / f"{name}.json"), paths[name], seed=i, max_steps=STEPS)
    return paths


def test_round_trip(recorded):
    recording = read_recording(recorded["unicycle"])
    level = load_level(ROOT / "levels" / "unicycle.json")
    assert recording.metadata["player"] == "agent" and recording.metadata["name"] == "random"
    assert recording.metadata["seed"] == "1" and recording.metadata["size"] == "s"
    assert recording.env["frame_skip"] == level.params.frame_skip
    assert json.loads(recording.level_json)["name"] == json.loads(json.dumps(level.name))
    for a, b in zip(jax.tree.leaves(recording.level_file.level), jax.tree.leaves(level.level), strict=True):
        assert np.array_equal(np.asarray(a), np.asarray(b))
    t = recording.num_steps
    assert 0 < t <= STEPS and recording.summary["steps"] == t
    assert recording.actions.shape == (t, 6) and recording.actions.dtype == np.int32
    k = int(np.asarray(level.level.sim.bodies.active).sum())
    assert recording.position.shape == (t, k, 2) and recording.rotation.shape == (t, k)
    assert recording.terminated[-1] or recording.truncated[-1] or t == STEPS
    # frames: at most 10 Hz of simulated time, real JPEGs
    assert len(recording.frames) >= 1 and recording.frames[0][:2] == b"\xff\xd8"
    assert np.all(np.diff(recording.frame_times) >= 0.1 - 1e-6)
    from_bytes = read_recording(recorded["unicycle"].read_bytes())
    assert np.array_equal(from_bytes.position, recording.position)


def test_foxglove_compressed_image_schema(recorded):
    from mcap.reader import make_reader

    with open(recorded["car_ramp"], "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        camera = [c for c in summary.channels.values() if c.topic == "/camera"][0]
        schema = summary.schemas[camera.schema_id]
        assert schema.name == "foxglove.CompressedImage" and schema.encoding == "jsonschema"
        assert camera.message_encoding == "json"
        properties = json.loads(schema.data)["properties"]
        assert properties["data"]["contentEncoding"] == "base64"
        assert {"timestamp", "frame_id", "format", "data"} <= set(properties)
        messages = [json.loads(m.data) for _, _, m in reader.iter_messages(topics=["/camera"])]
    assert messages
    for message in messages:
        assert set(message["timestamp"]) == {"sec", "nsec"} and 0 <= message["timestamp"]["nsec"] < 10**9
        assert message["format"] == "jpeg" and message["frame_id"]
        assert base64.b64decode(message["data"])[:2] == b"\xff\xd8"


@pytest.mark.parametrize("name", LEVELS)
def test_exact_replay(recorded, name):
    recording = read_recording(recorded[name], frames=False)
    check = verify(recording)
    assert check.ok, check.detail
    assert check.steps == recording.num_steps
    assert np.any(recording.velocity != 0)  # something moved: the comparison is not between two still scenes


def test_replay_detects_a_changed_action(recorded):
    recording = read_recording(recorded["thrust_hop"], frames=False)
    assert np.any(recording.actions[:, 4] == 1)  # random play fired the thruster at some step
    first = int(np.argmax(recording.actions[:, 4] == 1))
    recording.actions[first, 4] = 0
    check = verify(recording)
    assert not check.ok and check.divergent_step == first


def test_session_style_recording_with_step_no_reset(tmp_path):
    """The server may step with its own jitted env.step_no_reset; recorded states still replay bitwise."""
    level = load_level(ROOT / "levels" / "pendulum_swing.json")
    config = EnvConfig(size=level.size, frame_skip=level.params.frame_skip)
    env = make_env(config, level)
    params = EnvParams.from_level_params(level.params)
    step = jax2d.jit(env.step_no_reset)
    obs, state = env.reset(jax.random.PRNGKey(0), params)
    path = tmp_path / "session.mcap"
    with Recorder(path, level, metadata={"player": "human", "name": "test"}) as recorder:
        for i in range(40):
            action = np.array([1 + (i // 10) % 2, 0, 0, 0, 0, 0], np.int32)
            obs, state, reward, terminated, truncated, _ = step(jax.random.PRNGKey(i), state, action, params)
            recorder.add_step(action, reward, terminated, truncated, state)
    recording = read_recording(path)
    assert recording.metadata["player"] == "human" and recording.num_steps == 40
    check = verify(recording)
    assert check.ok, check.detail


def _foreign_mcap() -> bytes:
    buffer = io.BytesIO()
    writer = Writer(buffer)
    writer.start(profile="ros2", library="test")
    schema = writer.register_schema("x", "jsonschema", b"{}")
    channel = writer.register_channel("/chatter", "json", schema)
    writer.add_message(channel, 1, b"{}", 1)
    writer.finish()
    return buffer.getvalue()


def test_bad_files_get_clear_errors(recorded, tmp_path):
    good = recorded["thrust_hop"].read_bytes()
    cases = {
        "not mcap": (b"{\"level\": 1}\n" * 10, "not an MCAP file"),
        "truncated": (good[: len(good) // 2], "truncated"),
        "foreign": (_foreign_mcap(), "not a kinetix recording"),
        "empty": (b"", "not an MCAP file"),
    }
    corrupt = bytearray(good)
    middle = len(corrupt) // 2
    corrupt[middle:middle + 64] = bytes(64)
    cases["corrupt"] = (bytes(corrupt), "corrupt")
    for label, (data, words) in cases.items():
        with pytest.raises(RecordingError, match=words):
            read_recording(data)
        path = tmp_path / f"{label}.mcap"
        path.write_bytes(data)
        with pytest.raises(RecordingError, match=words):
            read_recording(path)
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(tmp_path / "missing.mcap")


def _inflating_mcap(payload: int, compression: CompressionType = CompressionType.ZSTD) -> bytes:
    """A kinetix-profile MCAP whose one message is `payload` zero bytes: tiny on disk, large once inflated."""
    buffer = io.BytesIO()
    writer = Writer(buffer, compression=compression, chunk_size=2 * payload)
    writer.start(profile="kinetix-recording", library="test")
    channel = writer.register_channel("/step", "json", writer.register_schema("x", "jsonschema", b"{}"))
    writer.add_message(channel, 1, bytes(payload), 1)
    writer.finish()
    return buffer.getvalue()


def test_compression_bombs_are_refused_before_inflating(monkeypatch):
    from kinetix.recording import reader

    monkeypatch.setattr(reader, "MAX_UNCOMPRESSED", 1 << 20)
    bomb = _inflating_mcap(8 << 20)
    assert len(bomb) < 8 << 10  # 8 MB of zeros in a few KB
    with pytest.raises(RecordingError, match="too large: it inflates to more than 1 MB"):
        read_recording(bomb)
    # A chunk that declares a small size but whose zstd frame says otherwise is caught by the frame's own size.
    small = _inflating_mcap(4 << 10)
    chunk = next(r for r in StreamReader(io.BytesIO(small), emit_chunks=True).records if isinstance(r, Chunk))
    # The chunk record comes before its index in the summary, so the first occurrence is the chunk's header.
    lying = small.replace(chunk.uncompressed_size.to_bytes(8, "little"), (16).to_bytes(8, "little"), 1)
    with pytest.raises(RecordingError, match=f"inflates to {chunk.uncompressed_size} bytes, declared 16"):
        read_recording(lying)
    with pytest.raises(RecordingError, match="'lz4' chunk compression"):
        read_recording(_inflating_mcap(4 << 10, CompressionType.LZ4))


def test_abort_and_exception_leave_nothing(tmp_path):
    level = load_level(ROOT / "levels" / "thrust_hop.json")
    state = level.level
    recorder = Recorder(tmp_path / "a.mcap", level, metadata={})
    recorder.add_step(np.zeros(6, np.int32), 0.0, False, False, state)
    recorder.abort()
    with pytest.raises(RuntimeError):
        with Recorder(tmp_path / "b.mcap", level, metadata={}) as recorder:
            recorder.add_step(np.zeros(6, np.int32), 0.0, False, False, state)
            raise RuntimeError("disconnect")
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(RecordingError, match="closed"):
        recorder.add_step(np.zeros(6, np.int32), 0.0, False, False, state)


def test_bad_state_fails_at_close_and_leaves_nothing(tmp_path):
    level = load_level(ROOT / "levels" / "thrust_hop.json")
    recorder = Recorder(tmp_path / "c.mcap", level, metadata={})
    recorder.add_step(np.zeros(6, np.int32), 0.0, False, False, "not a state")
    with pytest.raises(RecordingError, match="EnvState"):
        recorder.close()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("how", ["kill", "exception"])
def test_crash_leaves_no_file_at_the_target(tmp_path, how):
    target = tmp_path / "crash.mcap"
    ending = "os.kill(os.getpid(), signal.SIGKILL)" if how == "kill" else "raise SystemExit(3)"
    script = textwrap.dedent(f"""
        import os, signal, numpy as np
        from kinetix.levels import load_level
        from kinetix.recording import Recorder
        level = load_level({str(ROOT / "levels" / "thrust_hop.json")!r})
        recorder = Recorder({str(target)!r}, level, metadata={{}})
        for i in range(200):
            recorder.add_step(np.zeros(6, np.int32), 0.0, False, False, level.level)
        {ending}
    """)
    result = subprocess.run([sys.executable, "-c", script], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)},
                            capture_output=True, timeout=120)
    assert result.returncode == (-signal.SIGKILL if how == "kill" else 3), result.stderr.decode()
    assert not target.exists()
    from kinetix.recording import remove_partial_files

    leftovers = list(tmp_path.iterdir())
    assert all(p.name.startswith(".crash.mcap.") and p.suffix == ".part" for p in leftovers)
    assert leftovers or how != "kill"  # (an exception lets the exit handler delete it)
    assert remove_partial_files(tmp_path) == []  # seconds old: could be between its creation and its lock
    # Its writer is gone, so nobody owns it: removed however fresh, while a live recorder's file stays.
    live = Recorder(tmp_path / "live.mcap", load_level(ROOT / "levels" / "thrust_hop.json"), metadata={})
    try:
        assert sorted(remove_partial_files(tmp_path, min_age=0)) == sorted(leftovers)
        assert [p.name.startswith(".live.mcap.") for p in tmp_path.iterdir()] == [True]
    finally:
        live.close()
    assert [p.name for p in tmp_path.iterdir()] == ["live.mcap"]
    assert remove_partial_files(tmp_path, min_age=0) == []


def test_bad_recorder_arguments(tmp_path):
    level = load_level(ROOT / "levels" / "thrust_hop.json")
    with pytest.raises(RecordingError, match="does not exist"):
        Recorder(tmp_path / "no" / "x.mcap", level, metadata={})
    with pytest.raises(RecordingError, match="JSON"):
        Recorder(tmp_path / "x.mcap", level, metadata={"bad": object()})
    assert list(tmp_path.iterdir()) == []


def test_export_demos(recorded, tmp_path):
    out = tmp_path / "demos"
    inputs = [str(recorded["thrust_hop"]), str(recorded["unicycle"])]
    manifest = export_demos(inputs, out, obs="flat", log=lambda *_: None)
    assert (out / "manifest.json").is_file() and json.loads((out / "manifest.json").read_text()) == manifest
    assert manifest["size"] == "s" and manifest["observation"] == "flat" and len(manifest["episodes"]) == 2
    data = np.load(out / manifest["shards"][0]["file"])
    total = sum(read_recording(p, frames=False).num_steps for p in inputs)
    assert manifest["steps"] == total and data["rewards"].shape == (total,)
    assert data["obs"].shape[0] == total and data["obs"].ndim == 2 and data["obs"].dtype == np.float32
    assert data["actions"].shape == (total, 6)
    assert data["dones"].dtype == bool and np.array_equal(data["dones"], data["terminated"] | data["truncated"])
    assert set(np.unique(data["episode"])) == {0, 1}
    # the first observation of each episode is the level's initial one, not a later state
    from kinetix.observations import observe

    first = np.asarray(observe(load_level(ROOT / "levels" / "thrust_hop.json").level, "flat"))
    assert np.array_equal(data["obs"][0], first)
    with pytest.raises(RecordingError, match="already exists"):
        export_demos(inputs, out)
    solved = [p for p in inputs if read_recording(p, frames=False).solved]
    if solved:
        kept = export_demos(inputs, tmp_path / "solved", solved_only=True, log=lambda *_: None)
        assert [e["file"] for e in kept["episodes"]] == solved
    else:
        with pytest.raises(RecordingError, match="none of the 2 recordings"):
            export_demos(inputs, tmp_path / "solved", solved_only=True)
        assert not (tmp_path / "solved").exists()


def test_export_demos_entity_observations(recorded, tmp_path):
    manifest = export_demos([str(recorded["thrust_hop"])], tmp_path / "e", obs="entity", log=lambda *_: None)
    data = np.load(tmp_path / "e" / manifest["shards"][0]["file"])
    names = {k for k in data.files if k.startswith("obs_")}
    assert names and all(data[k].shape[0] == manifest["steps"] for k in names)


def test_cli_replay_exit_codes(recorded, tmp_path, capsys):
    from kinetix.cli import main

    assert main(["replay", str(recorded["unicycle"]), "--gif", str(tmp_path / "u.gif"), "--resolution", "64"]) == 0
    assert "matches" in capsys.readouterr().out
    from PIL import Image

    with Image.open(tmp_path / "u.gif") as gif:
        assert gif.n_frames > 1 and gif.size == (64, 64)
    # states that were never simulated (the level standing still while the actions say otherwise) diverge
    level = load_level(ROOT / "levels" / "unicycle.json")
    fake = tmp_path / "fake.mcap"
    with Recorder(fake, level, metadata={}) as recorder:
        for _ in range(5):
            recorder.add_step(np.array([1, 0, 0, 0, 0, 0], np.int32), 0.0, False, False, level.level)
    assert main(["replay", str(fake)]) == 1
    assert "diverges at step 0" in capsys.readouterr().out
    (tmp_path / "text.mcap").write_text("hello")
    assert main(["replay", str(tmp_path / "text.mcap")]) == 2
    assert "not an MCAP file" in capsys.readouterr().err


def test_cli_replay_writes_an_mp4(recorded, tmp_path, capsys):
    from kinetix.cli import main
    from kinetix.recording import read_recording

    out = tmp_path / "u.mp4"
    assert main(["replay", str(recorded["unicycle"]), "--mp4", str(out), "--resolution", "64"]) == 0
    assert "matches" in capsys.readouterr().out
    frames = _decode_video(out, 64)  # decoded back through ffmpeg: a real H.264 video, not just a file
    recording = read_recording(recorded["unicycle"])
    assert frames.shape[1:] == (64, 64, 3)
    assert 2 <= frames.shape[0] <= recording.num_steps + 1
    assert frames.std(axis=0).max() > 0  # the picture changes over the play
    assert not list(tmp_path.glob("*.part*"))  # written under a temporary name, then renamed


def _decode_video(path, size: int) -> np.ndarray:
    """(frames, size, size, 3) RGB, decoded by the ffmpeg binary (started without Python in the forked child)."""
    import imageio_ffmpeg

    out = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-i", str(path), "-f", "rawvideo",
                          "-pix_fmt", "rgb24", "-"], capture_output=True, check=True, timeout=60).stdout
    return np.frombuffer(out, np.uint8).reshape(-1, size, size, 3)


def test_mp4_writing_forks_no_python_and_fails_cleanly(recorded, tmp_path):
    """ffmpeg starts without running Python in a forked child (JAX warns of a deadlock hazard there), and a
    failing ffmpeg gives a RecordingError that quotes it, with nothing left at the target or beside it."""
    from kinetix.recording import read_recording
    from kinetix.recording.replay import write_mp4

    recording = read_recording(recorded["unicycle"])
    with warnings.catch_warnings(record=True) as caught:  # JAX's fork hook warns; an error there is swallowed
        warnings.simplefilter("always")
        assert write_mp4(recording, tmp_path / "ok.mp4", resolution=32) >= 2
    assert not [w for w in caught if "fork" in str(w.message)]
    assert (tmp_path / "ok.mp4").stat().st_size > 0
    missing = tmp_path / "no-such-folder" / "u.mp4"
    with pytest.raises(RecordingError, match="ffmpeg failed writing .*u.mp4 .exit status [1-9]"):
        write_mp4(recording, missing, resolution=32)
    assert not missing.parent.exists() and sorted(p.name for p in tmp_path.iterdir()) == ["ok.mp4"]


def test_cli_play_records_noop(tmp_path, capsys):
    from kinetix.cli import main

    out = tmp_path / "noop.mcap"
    assert main(["play", "--agent", "noop", "--level", str(ROOT / "levels" / "thrust_hop.json"), "--record", str(out),
                 "--max-steps", "12", "--seed", "4"]) == 0
    recording = read_recording(out)
    assert recording.num_steps == 12 and not recording.actions.any() and recording.metadata["seed"] == "4"
    assert main(["play", "--agent", "noop", "--level", str(tmp_path / "missing.json"), "--record",
                 str(tmp_path / "x.mcap")]) == 2
    assert not (tmp_path / "x.mcap").exists()


def test_exact_replay_on_shared_kinetix_levels(shared_dir, tmp_path):
    """Public Kinetix levels with joints and thrusters (one per size class) replay bitwise."""
    for i, name in enumerate(["s/h1_thrust_over_ball.json", "m/h3_car_thrust.json", "l/hard_cartpole_thrust.json"]):
        path = shared_dir / "kinetix-levels" / name
        if not path.is_file():
            pytest.skip(f"{path} missing")
        out = tmp_path / f"{i}.mcap"
        play_episode("random", load_level(path), out, seed=i, max_steps=40, frames=False)
        check = verify(read_recording(out))
        assert check.ok, f"{name}: {check.detail}"


def test_train_bc_writes_a_loadable_agent(recorded, tmp_path):
    pytest.importorskip("optax")
    from kinetix.agents import load_policy
    from kinetix.recording.bc import train_bc

    level = load_level(ROOT / "levels" / "car_ramp.json")
    play_episode("noop", level, tmp_path / "noop.mcap", max_steps=64, frames=False)
    export_demos([str(tmp_path / "noop.mcap")], tmp_path / "demos", obs="flat", log=lambda *_: None)
    result = train_bc(tmp_path / "demos", tmp_path / "agent", epochs=30, batch_size=16, lr=3e-3, log=lambda *_: None)
    # the untrained policy picks the whole demonstrated action with probability (1/3)^4 (1/2)^2 < 1 %
    assert result["accuracy"] > 0.9
    env = make_env(EnvConfig(size=level.size, observation="flat", frame_skip=level.params.frame_skip), level)
    policy = load_policy(str(tmp_path / "agent"), env)
    obs, _ = env.reset(jax.random.PRNGKey(0))
    actions = [np.asarray(policy.act(jax.random.PRNGKey(i), obs)[0]) for i in range(5)]
    assert all(env.action_space.contains(a) for a in actions)
    assert sum(not a.any() for a in actions) >= 3  # it learned to do nothing, as demonstrated
    epochs_run = []  # a bad learning rate is refused before any epoch runs, and nothing is written
    with pytest.raises(ValueError, match="lr must be a positive finite number"):
        train_bc(tmp_path / "demos", tmp_path / "bad", epochs=30, lr=-1e-3, log=epochs_run.append)
    assert epochs_run == [] and not (tmp_path / "bad").exists()


def test_recorded_level_matches_the_replayed_scene(recorded):
    from kinetix.recording import recorded_level, replay_states

    recording = read_recording(recorded["car_ramp"], frames=False)
    states = {i: state for i, state, _ in replay_states(recording)}
    for i in (0, recording.num_steps // 2, recording.num_steps - 1):
        got, want = recorded_level(recording, i).sim.bodies, states[i].level.sim.bodies
        assert np.array_equal(np.asarray(got.position), np.asarray(want.position))
        assert np.array_equal(np.asarray(got.angle), np.asarray(want.angle))
    with pytest.raises(IndexError):
        recorded_level(recording, recording.num_steps)


def test_batched_steps_replay_bitwise_with_the_batched_program(tmp_path):
    """The browser server steps several tabs in one vmapped call, whose results can differ bitwise from a single
    step: steps recorded with their batch size re-simulate bitwise; labelled as single steps, they verify exactly
    when the single-step program gives the same bits."""
    import jax.numpy as jnp

    level = load_level(ROOT / "levels" / "car_ramp.json")
    config = EnvConfig(size=level.size, frame_skip=level.params.frame_skip)
    env = make_env(config, level)
    params = EnvParams.from_level_params(level.params)
    many = jax2d.jit(jax.vmap(env.transition))  # as server.play.steps.Stepper's batched step: 8 lanes,
    # other plays in them
    state = env.initial_state(jax.random.PRNGKey(0), params)
    other = state
    stack = lambda *xs: jnp.stack(xs)  # noqa: E731
    steps = []
    for i in range(80):
        action = np.array([2 if i < 50 else 1, 0, 0, 0, 0, 0], np.int32)
        lanes = [state] + [other] * 7
        out = many(jax.tree.map(stack, *lanes), np.stack([action] + [np.zeros(6, np.int32)] * 7),
                   jax.tree.map(stack, *([params] * 8)))
        state, reward, terminated, truncated, _ = jax.tree.map(lambda x: x[0], out)
        other = jax.tree.map(lambda x: x[1], out[0])
        steps.append((action, reward, terminated, truncated, state))
    for label, path in ((8, tmp_path / "batched.mcap"), (1, tmp_path / "mislabelled.mcap")):
        with Recorder(path, level, metadata={"player": "human"}) as recorder:
            for step in steps:
                recorder.add_step(*step, batch=label)
    batched = read_recording(tmp_path / "batched.mcap")
    assert batched.batches.tolist() == [8] * 80
    check = verify(batched)
    assert check.ok, check.detail
    # Labelled as single steps, the recording verifies exactly when the single-step program, chained from the
    # start as verify does, gives the recorded bodies and rewards bitwise (the batched and the single program
    # may round alike, or not, depending on the scene).
    single = jax2d.jit(env.transition)
    state, alike = env.initial_state(jax.random.PRNGKey(0), params), True
    for action, reward, _, _, recorded in steps:
        state, replayed_reward, _, _, _ = single(state, action, params)
        got, want = state.level.sim.bodies, recorded.level.sim.bodies
        alike &= np.array_equal(np.asarray(replayed_reward), np.asarray(reward)) and all(
            np.array_equal(np.asarray(getattr(got, f)), np.asarray(getattr(want, f)))
            for f in ("position", "angle", "velocity", "angular_velocity"))
    assert verify(read_recording(tmp_path / "mislabelled.mcap")).ok == alike
