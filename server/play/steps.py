"""Keyboard play: held keys -> a multi-discrete action, and one compiled env step per (size class, frame_skip).

    stepper = stepper_for(level_file)          # compiled once per size class and frame skip, shared by sessions
    state, params = stepper.start(level_file)
    state, result = stepper.step(state, action_from_keys({"ArrowRight"}), params)

Keys: Left/Right drive motor binding 0, Up/Down binding 1, W/S binding 2, A/D binding 3; keys 1 and 2 fire
thruster bindings 0 and 1 while held. Opposite keys held together cancel. One rule on every level: the second key
of a pair (Right, Down, S, D) turns the binding's wheel clockwise, so Right makes a car roll right; the first
anticlockwise. Which binding value that is depends on the level's joints (kinetix.bindings.clockwise_values), so
pass `clockwise_values(level)` as `clockwise`; without it the second key gives -1 (the value that turns a wheel
clockwise when it is the joint's body b, as in the public Kinetix levels).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
from typing import NamedTuple

import numpy as np

# key code -> (motor binding, turn): +1 turns the binding's wheel clockwise, -1 anticlockwise.
MOTOR_KEYS: dict[str, tuple[int, int]] = {
    "ArrowLeft": (0, -1), "ArrowRight": (0, 1),
    "ArrowUp": (1, -1), "ArrowDown": (1, 1),
    "KeyW": (2, -1), "KeyS": (2, 1),
    "KeyA": (3, -1), "KeyD": (3, 1),
}
DEFAULT_CLOCKWISE = np.full(4, -1, np.int32)  # the binding values that turn clockwise when the level is not known
THRUSTER_KEYS: dict[str, int] = {"Digit1": 0, "Digit2": 1, "Numpad1": 0, "Numpad2": 1}
PLAY_KEYS = frozenset(MOTOR_KEYS) | frozenset(THRUSTER_KEYS)
# Batched steps are compiled for these batch sizes; a batch is padded up to the next one (a larger batch is
# split). Each size is one more compile (8-15 s cold, about 1 s from the persistent cache, and a few hundred MB
# of peak memory while it runs), done in the background after start; until then plays step one by one.
BATCH_BUCKETS = (8,)
MIN_BATCH = 3  # fewer plays step one by one: padding 2 plays to 8 costs more than it saves (size m: 3.6 ms
               # one by one, 4.1 ms as a batch of 8)

log = logging.getLogger(__name__)


def action_from_keys(held: set[str] | frozenset[str], clockwise=None) -> np.ndarray:
    """The multi-discrete action (4 motor bindings in {0, 1, 2}, 2 thruster bindings in {0, 1}) for held keys.

    `clockwise`: per motor binding, the binding value (+1 or -1) that turns its wheel clockwise
    (kinetix.bindings.clockwise_values of the level played); default DEFAULT_CLOCKWISE.
    """
    clockwise = DEFAULT_CLOCKWISE if clockwise is None else clockwise
    action = np.zeros(6, np.int32)
    for binding in range(4):
        turns = {turn for code, (b, turn) in MOTOR_KEYS.items() if b == binding and code in held}
        if len(turns) == 1:  # both directions held cancel out
            value = turns.pop() * int(clockwise[binding])
            action[binding] = 1 if value > 0 else 2  # multi-discrete: 1 drives at +1, 2 at -1
    for code, binding in THRUSTER_KEYS.items():
        if code in held:
            action[4 + binding] = 1
    return action


class Motion(NamedTuple):
    """Host copies of the bodies' motion after a step, fetched in the same transfer as the step's numbers: drawing
    the frame and recording the step read these instead of fetching from the state again (measured with 8 plays:
    the per-play fetches were a fifth of the play thread's time)."""

    position: np.ndarray  # (N, 2)
    angle: np.ndarray  # (N,)
    velocity: np.ndarray  # (N, 2)
    angular_velocity: np.ndarray  # (N,)


def _motion_arrays(state) -> tuple:
    b = state.level.sim.bodies
    return b.position, b.angle, b.velocity, b.angular_velocity


@dataclasses.dataclass(frozen=True)
class StepResult:
    reward: float
    terminated: bool
    truncated: bool
    solved: bool
    failed: bool
    timestep: int
    # Stepped alone (1) or in a compiled batch of this many plays, whose numbers can differ in the last bits:
    # recordings note it so replay steps the same way. Not part of equality (the same step outcome).
    batch: int = dataclasses.field(default=1, compare=False)
    motion: Motion | None = dataclasses.field(default=None, compare=False, repr=False)  # of the state after it


class Stepper:
    """The jitted `transition` of a KinetixEnv for one size class, frame skip and solver (no reset, no observation)."""

    def __init__(self, size, frame_skip: int, solver=None):
        import jax2d
        from kinetix.devices import on_interactive_device
        from kinetix.env import EnvConfig, make_env
        from kinetix.level import WALLS_SOLVER, empty_level

        self.size, self.frame_skip = size, frame_skip
        self.env = make_env(EnvConfig(size=size, frame_skip=frame_skip, solver=solver or WALLS_SOLVER),
                            empty_level(size))
        # One scene steps faster on the CPU than on a GPU (kinetix.devices.interactive_device); a no-op without one.
        self._transition = on_interactive_device(jax2d.jit(self.env.transition))
        self._initial = on_interactive_device(jax2d.jit(self._initial_state))
        self._batched: dict[int, object] = {}  # bucket -> compiled batched transition, once ready
        self._compiling: set[int] = set()
        self._failed: set[int] = set()  # compiles that failed are not retried (logged once)
        self._lock = threading.Lock()

    @staticmethod
    def _initial_state(level):
        import jax.numpy as jnp

        from kinetix.env import EnvState
        from kinetix.goal import goal_distance

        return EnvState(level=level, timestep=jnp.asarray(0, jnp.int32),
                        last_distance=goal_distance(level).astype(jnp.float32))

    def start(self, level_file):
        """(env state, env params) of a fresh episode of this level file."""
        from kinetix.env import EnvParams

        return self._initial(level_file.level), EnvParams.from_level_params(level_file.params)

    def step(self, state, action: np.ndarray, params):
        """(next state, StepResult) for one agent step (frame_skip physics steps)."""
        import jax

        next_state, reward, terminated, truncated, info = self._transition(state, action, params)
        (reward, terminated, truncated, solved, failed, timestep), motion = jax.device_get(
            ((reward, terminated, truncated, info["solved"], info["failed"], info["timestep"]),
             _motion_arrays(next_state)))
        return next_state, StepResult(float(reward), bool(terminated), bool(truncated), bool(solved), bool(failed),
                                      int(timestep), motion=Motion(*motion))

    def step_many(self, states: list, actions: list[np.ndarray], params: list) -> list[tuple[object, StepResult]]:
        """`step` for several independent plays at once: one compiled call per batch when its size is compiled.

        The plays may be different levels of this size class. States are stacked and split inside the compiled
        function, so the host passes and receives plain per-play states. Until the batch size's program is
        compiled (in the background, on first need) the plays step one by one, so nobody waits for a compile.
        """
        import jax

        results: list[tuple[object, StepResult]] = []
        start = 0
        while start < len(states):
            n = min(len(states) - start, BATCH_BUCKETS[-1])
            chunk = slice(start, start + n)
            start += n
            bucket = next(b for b in BATCH_BUCKETS if b >= n) if n >= MIN_BATCH else 1
            fn = self._batched_fn(bucket) if bucket > 1 else None
            if fn is None:
                results += [self.step(s, a, p) for s, a, p in zip(states[chunk], actions[chunk], params[chunk],
                                                                  strict=True)]
                continue
            pad = bucket - n  # padded with copies of the first play; their results are dropped
            outs = fn(tuple(states[chunk]) + (states[chunk.start],) * pad,
                      np.stack(list(actions[chunk]) + [actions[chunk.start]] * pad),
                      tuple(params[chunk]) + (params[chunk.start],) * pad)
            next_states, numbers, motion = outs
            (reward, terminated, truncated, solved, failed, timestep), motion = jax.device_get((numbers, motion))
            results += [(next_states[i], StepResult(float(reward[i]), bool(terminated[i]), bool(truncated[i]),
                                                    bool(solved[i]), bool(failed[i]), int(timestep[i]), bucket,
                                                    Motion(*(x[i] for x in motion))))
                        for i in range(n)]
        return results

    def _batched_fn(self, bucket: int):
        """The compiled batched transition for `bucket` plays, or None while it compiles (started on first ask)."""
        with self._lock:
            fn = self._batched.get(bucket)
            if fn is not None or bucket in self._compiling or bucket in self._failed:
                return fn
            self._compiling.add(bucket)
        _start_compile(self._compile_batched, bucket)
        return None

    def _compile_batched(self, bucket: int) -> None:
        import time

        import jax
        import jax.numpy as jnp

        import jax2d
        from kinetix.devices import on_interactive_device

        transition = self.env.transition

        def many(states, actions, params):
            stack = lambda *xs: jnp.stack(xs)  # noqa: E731
            batched = jax.vmap(transition)(jax.tree.map(stack, *states), actions, jax.tree.map(stack, *params))
            next_state, reward, terminated, truncated, info = batched
            split = tuple(jax.tree.map(lambda x, i=i: x[i], next_state) for i in range(bucket))
            numbers = (reward, terminated, truncated, info["solved"], info["failed"], info["timestep"])
            return split, numbers, _motion_arrays(next_state)

        try:
            t0 = time.perf_counter()
            fn = on_interactive_device(jax2d.jit(many))  # a few plays: the CPU's, like the single step
            # Compile with real shapes: a fresh episode of the empty level, as warm_up does.
            from kinetix.level import LevelFile, LevelParams, empty_level

            state, params = self.start(LevelFile(empty_level(self.size), LevelParams(frame_skip=self.frame_skip)))
            jax.block_until_ready(fn((state,) * bucket, np.zeros((bucket, 6), np.int32), (params,) * bucket))
            log.info("compiled the %d-play batched step for size %s in %.1f s", bucket, self.size.name,
                     time.perf_counter() - t0)
            with self._lock:
                self._batched[bucket] = fn
        except Exception:
            log.exception("could not compile the %d-play batched step; plays step one by one", bucket)
            with self._lock:
                self._failed.add(bucket)
        finally:
            with self._lock:
                self._compiling.discard(bucket)

    def warm_up(self) -> None:
        """Compile now (two steps: the second call can retrace when the level's dtypes settle)."""
        from kinetix.level import LevelFile, LevelParams, empty_level

        level_file = LevelFile(empty_level(self.size), LevelParams(frame_skip=self.frame_skip))
        state, params = self.start(level_file)
        for _ in range(2):
            state, _ = self.step(state, np.zeros(6, np.int32), params)


_COMPILES: list[threading.Thread] = []  # background compiles (see wait_for_compiles)
_COMPILES_LOCK = threading.Lock()


def _start_compile(target, *args) -> threading.Thread:
    # Not a daemon: interpreter exit waits for it (a compile cut off by shutdown aborts the whole process).
    thread = threading.Thread(target=target, args=args, name="kinetix-compile")
    with _COMPILES_LOCK:
        _COMPILES[:] = [t for t in _COMPILES if t.is_alive()]
        _COMPILES.append(thread)
    thread.start()
    return thread


def wait_for_compiles(timeout: float | None = None) -> bool:
    """Wait for background compiles to finish (server shutdown, benchmarks); False if some still run."""
    import time

    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        with _COMPILES_LOCK:
            running = [t for t in _COMPILES if t.is_alive()]
        if not running:
            return True
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            return False
        running[0].join(timeout=left)


def warm_batches(sizes=("s", "m", "l"), frame_skip: int = 2) -> None:
    """Compile the batched play steps for these size classes now, one after another, so several tabs playing at
    once are batched from the start (server.play.warmup runs this on its background thread)."""
    from kinetix.level import LevelFile, LevelParams, empty_level, size_class

    for name in sizes:
        stepper = stepper_for(LevelFile(empty_level(size_class(name)), LevelParams(frame_skip=frame_skip)))
        for bucket in BATCH_BUCKETS:
            with stepper._lock:
                if bucket in stepper._batched or bucket in stepper._compiling or bucket in stepper._failed:
                    continue
                stepper._compiling.add(bucket)
            stepper._compile_batched(bucket)


def warm_batches_in_background(sizes=("s", "m", "l"), frame_skip: int = 2, then=None) -> None:
    """`warm_batches` on a background compile thread without holding up the caller; then `then()` there."""

    def compile_all() -> None:
        warm_batches(sizes, frame_skip)
        if then is not None:
            then()

    _start_compile(compile_all)


_STEPPERS: dict[tuple, Stepper] = {}  # (size, frame skip, solver)
_STEPPERS_LOCK = threading.Lock()


def stepper_for(level_file) -> Stepper:
    """The shared Stepper for this level file's size class, frame skip and solver.

    Levels with the standard static walls (nearly all) share the WALLS_SOLVER program; a level with a moving
    body in polygon slots 0-3 gets one with the plain solver (kinetix.level.solver_for)."""
    from kinetix.level import solver_for

    size = level_file.size
    solver = solver_for(level_file.level)
    key = (size.name if size.name != "custom" else repr(size), int(level_file.params.frame_skip), solver)
    with _STEPPERS_LOCK:
        if key not in _STEPPERS:
            _STEPPERS[key] = Stepper(size, key[1], solver)
        return _STEPPERS[key]


def warm_up(sizes=("s", "m", "l"), frame_skip: int = 2) -> None:
    """Compile the play step for these size classes so the first play in the browser starts at once."""
    from kinetix.level import LevelFile, LevelParams, empty_level, size_class

    for name in sizes:
        stepper_for(LevelFile(empty_level(size_class(name)), LevelParams(frame_skip=frame_skip))).warm_up()
