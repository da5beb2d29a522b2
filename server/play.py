"""Keyboard play: held keys -> a multi-discrete action, and one compiled env step per (size class, frame_skip).

    stepper = stepper_for(level_file)          # compiled once per size class and frame skip, shared by sessions
    state, params = stepper.start(level_file)
    state, result = stepper.step(state, action_from_keys({"ArrowRight"}), params)

Keys (CONTRACT section 4): Left/Right drive motor binding 0 (+1/-1), Up/Down binding 1, W/S binding 2,
A/D binding 3; keys 1 and 2 fire thruster bindings 0 and 1 while held. Opposite keys held together cancel.
"""

from __future__ import annotations

import dataclasses
import threading

import numpy as np

# key code -> (motor binding, multi-discrete value): 1 drives the motor at +1, 2 at -1.
MOTOR_KEYS: dict[str, tuple[int, int]] = {
    "ArrowLeft": (0, 1), "ArrowRight": (0, 2),
    "ArrowUp": (1, 1), "ArrowDown": (1, 2),
    "KeyW": (2, 1), "KeyS": (2, 2),
    "KeyA": (3, 1), "KeyD": (3, 2),
}
THRUSTER_KEYS: dict[str, int] = {"Digit1": 0, "Digit2": 1, "Numpad1": 0, "Numpad2": 1}
PLAY_KEYS = frozenset(MOTOR_KEYS) | frozenset(THRUSTER_KEYS)


def action_from_keys(held: set[str] | frozenset[str]) -> np.ndarray:
    """The multi-discrete action (4 motor bindings in {0, 1, 2}, 2 thruster bindings in {0, 1}) for held keys."""
    action = np.zeros(6, np.int32)
    for binding in range(4):
        values = {value for code, (b, value) in MOTOR_KEYS.items() if b == binding and code in held}
        if len(values) == 1:  # both directions held cancel out
            action[binding] = values.pop()
    for code, binding in THRUSTER_KEYS.items():
        if code in held:
            action[4 + binding] = 1
    return action


@dataclasses.dataclass(frozen=True)
class StepResult:
    reward: float
    terminated: bool
    truncated: bool
    solved: bool
    failed: bool
    timestep: int


class Stepper:
    """The jitted `transition` of a KinetixEnv for one size class and frame skip (no reset, no observation)."""

    def __init__(self, size, frame_skip: int):
        import jax

        from kinetix.env import EnvConfig, make_env
        from kinetix.level import empty_level

        self.size, self.frame_skip = size, frame_skip
        self.env = make_env(EnvConfig(size=size, frame_skip=frame_skip), empty_level(size))
        self._transition = jax.jit(self.env.transition)
        self._initial = jax.jit(self._initial_state)

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
        reward, terminated, truncated, solved, failed, timestep = jax.device_get(
            (reward, terminated, truncated, info["solved"], info["failed"], info["timestep"]))
        return next_state, StepResult(float(reward), bool(terminated), bool(truncated), bool(solved), bool(failed),
                                      int(timestep))

    def warm_up(self) -> None:
        """Compile now (two steps: the second call can retrace when the level's dtypes settle)."""
        from kinetix.level import LevelFile, LevelParams, empty_level

        level_file = LevelFile(empty_level(self.size), LevelParams(frame_skip=self.frame_skip))
        state, params = self.start(level_file)
        for _ in range(2):
            state, _ = self.step(state, np.zeros(6, np.int32), params)


_STEPPERS: dict[tuple[str, int], Stepper] = {}
_STEPPERS_LOCK = threading.Lock()


def stepper_for(level_file) -> Stepper:
    """The shared Stepper for this level file's size class and frame skip."""
    size = level_file.size
    key = (size.name if size.name != "custom" else repr(size), int(level_file.params.frame_skip))
    with _STEPPERS_LOCK:
        if key not in _STEPPERS:
            _STEPPERS[key] = Stepper(size, key[1])
        return _STEPPERS[key]


def warm_up(sizes=("s", "m", "l"), frame_skip: int = 2) -> None:
    """Compile the play step for these size classes so the first play in the browser starts at once."""
    from kinetix.level import LevelFile, LevelParams, empty_level, size_class

    for name in sizes:
        stepper_for(LevelFile(empty_level(size_class(name)), LevelParams(frame_skip=frame_skip))).warm_up()
