"""The range of every numeric field of a level: one table, checked in one place (`kinetix.formats.build`).

Every way a level comes in goes through `build`: the loader (`load_level`, so `kinetix validate` and the
gallery API too), resizing, the browser editor's every edit and upload. The readers of the two file formats
only check types and finiteness; the bounds live here, so a field cannot be bounded in one path and
unbounded in another. docs/level-format.md lists this table (a test keeps the two equal).

Why bounds at all: a value far outside what any level needs either breaks the program (an episode length
beyond int32 overflows the step counter; a frame skip of 1e6 or a time step of 1e6 turns one play tick into
minutes of work) or only produces a scene float32 physics cannot simulate. The bounds are generous: every
level in levels/ and every published Kinetix level is well inside them (a test checks that).
"""

from __future__ import annotations

import dataclasses
import math

from kinetix.level import LevelError


@dataclasses.dataclass(frozen=True)
class Range:
    low: float
    high: float
    integer: bool = False
    unit: str = ""

    def text(self) -> str:
        return f"[{_g(self.low)}, {_g(self.high)}]"


def _g(x: float) -> str:
    """A bound as people write it: 100000, 0.001, 1e+06."""
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e7 else f"{x:g}"


# Body-frame lengths (vertices, anchors) and world coordinates. The world is 5 m x 5 m and its walls reach
# about 10 m from the origin; a body 100 m away has left it for good.
_COORDINATE = Range(-100.0, 100.0, unit="m")
_LOCAL = Range(-50.0, 50.0, unit="m")
# Angles are not wrapped (a wheel may have turned many times); 1000 rad keeps float32 precision near 1e-4 rad.
_ANGLE = Range(-1000.0, 1000.0, unit="rad")

# Keyed by what the field is, not by where a format keeps it: "<entity>.<field>". Vectors apply the range
# to each component.
RANGES: dict[str, Range] = {
    "env.max_timesteps": Range(1, 100_000, integer=True, unit="agent steps"),  # far below int32 overflow
    "env.frame_skip": Range(1, 16, integer=True, unit="physics steps"),  # compiled into the step: cost x skip
    "env.dense_reward_scale": Range(0.0, 10.0),
    "env.physics.dt": Range(0.001, 0.1, unit="s"),
    "env.physics.base_motor_speed": Range(0.0, 1_000.0, unit="rad/s"),
    "env.physics.base_motor_power": Range(0.0, 1_000_000.0),
    "env.physics.base_thruster_power": Range(0.0, 100_000.0, unit="N"),
    "gravity": Range(-100.0, 100.0, unit="m/s²"),
    "body.position": _COORDINATE,
    "body.angle": _ANGLE,
    "body.vertices": _LOCAL,
    "body.radius": Range(0.001, 50.0, unit="m"),
    "body.density": Range(0.001, 1_000.0, unit="kg/m²"),
    "body.friction": Range(0.0, 10.0),
    "body.restitution": Range(0.0, 1.0),
    "body.velocity": Range(-1_000.0, 1_000.0, unit="m/s"),
    "body.angular_velocity": Range(-1_000.0, 1_000.0, unit="rad/s"),
    "joint.anchor_a": _LOCAL,
    "joint.anchor_b": _LOCAL,
    "joint.ref_angle": _ANGLE,
    "joint.motor.speed": Range(-100.0, 100.0, unit="x base_motor_speed"),
    "joint.motor.power": Range(0.0, 100.0, unit="x base_motor_power"),
    "joint.limits": Range(-4 * math.pi, 4 * math.pi, unit="rad"),  # two turns either way, with float32 slack
    "thruster.anchor": _LOCAL,
    "thruster.angle": _ANGLE,
    "thruster.power": Range(0.0, 100.0, unit="x base_thruster_power"),
}


def check(key: str, value, where: str) -> None:
    """Raise LevelError naming `where` unless `value` (a number or a sequence of numbers) lies in RANGES[key]."""
    bounds = RANGES[key]
    values = value if isinstance(value, (list, tuple)) else [value]
    for k, x in enumerate(values):
        if isinstance(x, (list, tuple)):  # a list of vectors (polygon vertices)
            check(key, x, f"{where}[{k}]")
            continue
        place = f"{where}[{k}]" if value is values else where
        number = isinstance(x, (int, float)) and not isinstance(x, bool)
        # An int is compared as it is: math.isfinite(10**400) would raise OverflowError.
        if not (number and (isinstance(x, int) or math.isfinite(x)) and bounds.low <= x <= bounds.high):
            raise LevelError(f"{place}: {_value_text(x)} is out of range {bounds.text()}")
        if bounds.integer and not float(x).is_integer():
            raise LevelError(f"{place}: expected an integer, got {x!r}")


def _value_text(x) -> str:
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        return repr(x)
    return str(x) if isinstance(x, int) else f"{x:g}"
