"""Agents playing in a tab: "Watch agent" (AgentController) and "Race the agent" (RaceController).

Both are server.play.session Controllers: the session's play thread calls `act(state, params)` once per agent step
(every 1/30 s at the default frame skip), so that call must be cheap. Per agent (network shape) and size class
ONE jitted function computes the observation from the env state and runs the policy:

    fn(params, key, step, state) -> (action, value)

Parameters are an argument, not constants, so the general agent and every specialist of the same network
shape share one compile (and the persistent compile cache); `warm_in_background` compiles the general agent's
for the server's size classes at start, so the first "Watch agent" does not stall on a compile.

A race: the human plays the session's own play (keys as usual); the agent plays a second state of the same
level from the same start, stepped in lockstep inside `act` (same tick, same number of steps). Each side stops
when its episode ends; the race ends when someone solves (both at the same step: a tie) or both sides have
ended. The frame is split: human left, agent right, each labelled, and the winner is shown across both.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import deque
from collections.abc import Callable

import numpy as np
from PIL import Image, ImageDraw

from server.play import draw
from server.play.hooks import Controller, episode_end

log = logging.getLogger(__name__)

MOTOR_SYMBOL = {0: "0", 1: "+", 2: "-"}  # multi-discrete motor values (server.play.steps: 1 drives at +1, 2 at -1)

_FNS: dict[tuple, Callable] = {}  # (policy signature, size, observation) -> jitted (params, key, step, state)
_ENVS: dict[tuple, object] = {}  # (size, observation) -> a KinetixEnv used only to observe states
_POLICIES: dict[tuple, object] = {}  # (spec, size) -> Policy (checkpoints are read once)
_LOCK = threading.Lock()


def _size_key(size) -> str:
    return size.name if size.name != "custom" else repr(size)


def observing_env(size, observation: str = "entity"):
    """A KinetixEnv of this size class whose `observe` computes the agent's observation of a play state."""
    from kinetix.env import EnvConfig, make_env
    from kinetix.level import empty_level

    key = (_size_key(size), observation)
    with _LOCK:
        if key not in _ENVS:
            _ENVS[key] = make_env(EnvConfig(size=size, observation=observation), empty_level(size))
        return _ENVS[key]


def policy_for(spec: str, size):
    """`load_policy(spec, env)` for this size class, cached (a checkpoint is read from disk once)."""
    from kinetix.agents.policy import load_policy, required_observation

    key = (str(spec), _size_key(size))  # run directories are never rewritten, so a path names one agent
    with _LOCK:
        policy = _POLICIES.get(key)
    if policy is None:
        observation = required_observation(spec) or "entity"
        policy = load_policy(str(spec), observing_env(size, observation))
        with _LOCK:
            _POLICIES[key] = policy
    return policy


def step_fn(policy, size) -> Callable:
    """The jitted observe-and-act function for this policy's signature and size class (built once)."""
    import jax

    import jax2d

    observation = policy.observation or "entity"
    key = (policy.signature, _size_key(size), observation)
    with _LOCK:
        fn = _FNS.get(key)
    if fn is not None:
        return fn
    env = observing_env(size, observation)

    def observe_and_act(params, base_key, step, state):
        return policy.apply(params, jax.random.fold_in(base_key, step), env.observe(state))

    fn = jax2d.jit(observe_and_act)
    with _LOCK:
        return _FNS.setdefault(key, fn)


class AgentRunner:
    """One agent playing one state: `act(state) -> action` (numpy), remembering the last action and value."""

    def __init__(self, spec: str, size, *, label: str | None = None, seed: int = 0, policy=None):
        import jax

        self.spec = str(spec)
        self.policy = policy if policy is not None else policy_for(spec, size)
        self.label = label or self.policy.name
        self._fn = step_fn(self.policy, size)
        self._key = jax.random.key(seed)
        self._step = 0
        self.action: np.ndarray | None = None
        self.value: float | None = None
        self.step_seconds: deque[float] = deque(maxlen=1000)  # wall time of recent act calls (benchmarks)
        self._pending: tuple | None = None  # (state, its action and value being computed) from prefetch

    def warm(self, state) -> None:
        """Compile (if needed) and run the agent once on `state`, here and now: called before a play starts, so a
        compile never stalls the play thread (which steps every tab)."""
        import jax

        jax.block_until_ready(self._fn(self.policy.params, self._key, self._step, state))

    def prefetch(self, state) -> None:
        """Start computing the action for `state` now; `act(state)` collects it.

        JAX dispatches the jitted call asynchronously, so the agent thinks while the play thread draws and sends
        the frame of `state`, and the next tick only waits for what is left of it.
        """
        self._pending = (state, self._fn(self.policy.params, self._key, self._step, state))

    def act(self, state) -> np.ndarray:
        import jax

        t0 = time.perf_counter()
        pending, self._pending = self._pending, None
        if pending is not None and pending[0] is state:
            out = pending[1]
        else:
            out = self._fn(self.policy.params, self._key, self._step, state)
        action, value = jax.device_get(out)
        self._step += 1
        self.action = np.asarray(action, np.int32).reshape(-1)
        self.value = float(value)
        self.step_seconds.append(time.perf_counter() - t0)
        return self.action

    def describe(self, scene: draw.Scene | None = None) -> str:
        """The last action per binding of the level (every binding when `scene` is None) and the value estimate,
        e.g. 'M0 + M2 - T0 on  V +0.42'."""
        if self.action is None:
            return "(no action yet)"
        bindings = draw.used_bindings(scene) if scene is not None else None
        return f"{action_text(self.action, bindings)}  V {self.value:+.2f}"


def action_text(action: np.ndarray, bindings: tuple[set[int], set[int]] | None = None) -> str:
    """A multi-discrete action per binding: motors (+, -, 0) and thrusters (on, off); with `bindings` (motor and
    thruster bindings, draw.used_bindings) only those the level uses, as the overlay box lists them."""
    action = np.asarray(action).reshape(-1)
    if action.shape[0] != 6:
        return " ".join(str(int(a)) for a in action)
    motor_bindings, thruster_bindings = bindings if bindings is not None else (range(4), range(2))
    motors = [f"M{b} {MOTOR_SYMBOL.get(int(action[b]), '?')}" for b in sorted(motor_bindings)]
    thrusters = [f"T{b} {'on' if action[4 + b] else 'off'}" for b in sorted(thruster_bindings)]
    return " ".join(motors + thrusters) or "(no controls)"


def overlay_rows(action: np.ndarray, value: float, title: str, scene: draw.Scene | None) -> list[tuple[str, tuple]]:
    """The overlay's rows (text, colour): the title, the action of each binding the level has (its active motors'
    and thrusters'; every binding when the scene is not known), and the value estimate."""
    motors, thrusters = draw.used_bindings(scene) if scene is not None else (set(range(4)), set(range(2)))
    rows = [(title, (20, 20, 20))]
    rows += [(f"motor {b}: {MOTOR_SYMBOL.get(int(action[b]), '?')}", draw.MOTOR_COLOURS[b]) for b in sorted(motors)]
    rows += [(f"thruster {b}: {'on' if action[4 + b] else 'off'}", draw.THRUSTER_COLOURS[b])
             for b in sorted(thrusters)]
    return rows + [(f"value {value:+.3f}", (20, 20, 20))]


def _overlay_box(frame: np.ndarray, runner: AgentRunner, title: str, view: draw.View | None = None,
                 scene: draw.Scene | None = None, under_legend: bool = False) -> np.ndarray:
    """Draw the agent's action per binding of the level (in the bindings' colours) and its value estimate at the
    top left of the level's area, under the HUD line (and under the key legend when the frame has one), where levels
    are mostly sky; not on the right, which the browser's control panel covers."""
    if runner.action is None or runner.action.shape[0] != 6:
        return frame
    image = Image.fromarray(frame)
    pen = ImageDraw.Draw(image)
    font = draw._font(12)
    rows = overlay_rows(runner.action, runner.value, title, scene)
    width, height = 140, 14 * len(rows) + 8
    ox, oy = view.origin if view is not None else (0.0, 0.0)
    legend_rows = sum(map(len, draw.used_bindings(scene))) if under_legend and scene is not None else 0
    x0, y0 = int(ox) + 6, int(oy) + draw.TEXT_TOP + draw.LEGEND_ROW * legend_rows + (4 if legend_rows else 0)
    if x0 + width > image.width or y0 + height > image.height:
        return frame
    pen.rectangle([x0, y0, x0 + width, y0 + height], fill=(255, 255, 255), outline=(60, 60, 60))
    for n, (text, colour) in enumerate(rows):  # a swatch in the binding's colour, dark text (yellow is unreadable)
        y = y0 + 4 + 14 * n
        if n not in (0, len(rows) - 1):
            pen.rectangle([x0 + 6, y + 2, x0 + 15, y + 11], fill=tuple(int(c) for c in colour), outline=(60, 60, 60))
        pen.text((x0 + 20, y), text, fill=(20, 20, 20), font=font)
    return np.asarray(image)


class AgentController(Controller):
    """Watch agent: the agent chooses every action of the session's play; the HUD and overlay show its choice."""

    def __init__(self, runner: AgentRunner):
        self.runner = runner
        self.player = f"agent:{runner.label}"
        self._scene: draw.Scene | None = None

    def act(self, state, params) -> np.ndarray:
        return self.runner.act(state)

    def episode_end(self, state, result) -> str | None:
        end = super().episode_end(state, result)
        if end is None:
            self.runner.prefetch(state)  # the next action is computed while this frame is drawn
        return end

    def hud(self) -> str:
        return self.runner.describe(self._scene)

    def draw(self, session, view: draw.View, banner: str) -> np.ndarray:
        state = session._play[1]
        self._scene = draw.scene_of(state.level, static_from=self._scene)
        banner = banner.replace("You won!", "The agent solved it!").replace("You lost.", "The agent failed.")
        frame = draw.draw_frame(self._scene, view, hud=session.hud(), banner=banner)
        return _overlay_box(frame, self.runner, f"agent {self.runner.label}"[:20], view, scene=self._scene,
                            under_legend=True)


@dataclasses.dataclass
class Side:
    """One racer's progress: its result once its episode ended, its step count and simulated seconds."""

    name: str
    result: str | None = None
    steps: int = 0
    seconds: float = 0.0
    state: object = None
    scene: draw.Scene | None = None

    @property
    def solved(self) -> bool:
        return self.result == "solved"


WINNER_TEXT = {"human": "You win!", "agent": "The agent wins!", "tie": "A tie: both solved it at the same step",
               "nobody": "Nobody solved it"}


class RaceController(Controller):
    """Race the agent: the session's play is the human's; the agent plays its own copy of the same start.

    `on_finish(race)` is called (on its own thread) once the race is decided, to record both plays.
    """

    player = "race"  # a race records its two plays itself (kind human and kind agent), see on_finish

    def __init__(self, session, runner: AgentRunner, stepper, state, params,
                 on_finish: Callable[[RaceController], None] | None = None):
        """`stepper`, `state`, `params`: the level's play stepper and the fresh start both sides begin from."""
        self.session = session
        self.runner = runner
        self.stepper = stepper
        self.tick = float(params.sim.dt) * stepper.frame_skip
        self.human = Side("human", state=state)
        self.agent = Side(f"agent:{runner.label}", state=state)  # the same start state (states are immutable)
        self.winner: str | None = None
        self.on_finish = on_finish
        self.gallery_id: str | None = None  # the gallery level raced on, if any (set by the caller)
        self.recorded = threading.Event()  # set once on_finish has recorded the plays

    def act(self, state, params) -> np.ndarray:
        if self.agent.result is None and self.winner is None:
            action = self.runner.act(self.agent.state)
            self.agent.state, result = self.stepper.step(self.agent.state, action, params)
            self.agent.steps, self.agent.seconds = result.timestep, result.timestep * self.tick
            self.agent.result = episode_end(result)
            if self.agent.result is None:
                self.runner.prefetch(self.agent.state)
        if self.human.result is not None:  # the human's episode ended: its side stays as it was
            return np.zeros(6, np.int32)
        return self.session.keys_action()

    def episode_end(self, state, result) -> str | None:
        if self.human.result is None:
            self.human.state = state
            self.human.steps, self.human.seconds = result.timestep, result.timestep * self.tick
            self.human.result = episode_end(result)
        if self.human.solved or self.agent.solved:
            self.winner = "tie" if self.human.solved and self.agent.solved else (
                "human" if self.human.solved else "agent")
        elif self.human.result is not None and self.agent.result is not None:
            self.winner = "nobody"
        if self.winner is None:
            return None
        if self.on_finish is not None:
            threading.Thread(target=self.on_finish, args=(self,), daemon=True).start()
        return self.human.result or "stopped"

    def hud(self) -> str:
        return f"race vs {self.runner.label}  agent: {self.runner.describe(self.agent.scene)}"

    def draw(self, session, view: draw.View, banner: str) -> np.ndarray:
        half = draw.View(max(view.width // 2 - 2, 32), view.height)  # a 4-pixel divider between the halves
        halves = []
        for side, label in ((self.human, "YOU"), (self.agent, f"AGENT {self.runner.label}"[:24])):
            state = side.state if side is self.agent or side.result is not None else session._play[1]
            steps = side.steps
            side.scene = draw.scene_of(state.level, static_from=side.scene)
            text = f"{label}  step {steps}  {steps * self.tick:.2f} s"
            end = "" if side.result is None else f"{draw_result(side.result)}\n{side.seconds:.2f} s"
            frame = draw.draw_frame(side.scene, half, hud=text, banner=end, legend=side is self.human)
            if side is self.agent:
                frame = _overlay_box(frame, self.runner, "agent", half, scene=side.scene)
            halves.append(frame)
        divider = np.full((view.height, view.width - 2 * half.width, 3), 60, np.uint8)
        frame = np.concatenate([halves[0], divider, halves[1]], axis=1)
        if self.winner is not None:
            frame = _winner_banner(frame, WINNER_TEXT[self.winner])
        elif session.mode == "ready":  # the race waits for the human's first key (session.START_HINT)
            frame = _winner_banner(frame, banner)
        return frame


def draw_result(result: str) -> str:
    return {"solved": "Solved!", "failed": "Failed", "truncated": "Time is up", "nan": "Broke"}.get(result, result)


RACE_BANNER_ROWS = (66, 28)  # the race's banner: from this many pixels above the canvas's bottom to this many


def race_banner_box(width: int, height: int) -> tuple[int, int, int, int]:
    """(left, top, right, bottom) of the race's banner ("Press Space ...", "You win!") in a frame of this size: a
    band near the bottom, clear of the notices at the top right of the canvas (static/frames.js), which covered it
    at the top (issue 37), and of each half's own result banner at mid-height."""
    return 0, height - RACE_BANNER_ROWS[0], width, height - RACE_BANNER_ROWS[1]


def _winner_banner(frame: np.ndarray, text: str) -> np.ndarray:
    image = Image.fromarray(frame)
    pen = ImageDraw.Draw(image)
    font = draw._font(22)
    width = pen.textlength(text, font=font)
    left, top, right, bottom = race_banner_box(image.width, image.height)
    pen.rectangle([left, top, right, bottom], fill=(255, 244, 200), outline=(60, 60, 60))
    pen.text((image.width / 2 - width / 2, top + 6), text, fill=(20, 20, 20), font=font)
    return np.asarray(image)


def warm_agent(sizes=("s", "m", "l"), spec: str = "general") -> None:
    """Compile the observe-and-act function of `spec` for these size classes now (server.play.warmup runs it
    after the play steps, on its background thread)."""
    from kinetix.level import LevelFile, LevelParams, empty_level, size_class
    from server.play import steps

    for name in sizes:
        try:
            size = size_class(name)
            runner = AgentRunner(spec, size)
            stepper = steps.stepper_for(LevelFile(empty_level(size), LevelParams()))
            state, _ = stepper.start(LevelFile(empty_level(size), LevelParams()))
            t0 = time.perf_counter()
            runner.act(state)
            runner.act(state)
            log.info("compiled agent %s for size %s in %.1f s", spec, name, time.perf_counter() - t0)
        except Exception:  # e.g. no general agent in this checkout: watching it then reports the error
            log.exception("could not compile agent %s for size %s", spec, name)


def warm_in_background(sizes=("s", "m", "l"), spec: str = "general", then: Callable[[], None] | None = None):
    """`warm_agent` on a background compile thread, then `then()` there."""
    from server.play import steps

    def compile_all() -> None:
        warm_agent(sizes, spec)
        if then is not None:
            then()

    return steps._start_compile(compile_all)
