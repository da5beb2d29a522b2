"""The edit-mode GUI in viser: tools, edit buttons, the property panel of the selection, level settings,
files, snapping and the size-class limits. The only module of the editor that imports viser.

Widgets call the editor under `lock` (pass the session's lock so GUI callbacks, which viser runs on a
thread pool, never interleave with pointer input) and then `on_change()` outside the lock.
`refresh()` writes the editor's state back into the widgets; while it runs, widget callbacks are ignored
(viser calls update callbacks synchronously when Python assigns a value).
"""

from __future__ import annotations

import contextlib
import math
import random
import threading
from collections.abc import Callable

import viser

from kinetix.level import ROLE_NAMES, SIZES
from server.editor.editor import TOOLS, Editor
from server.editor.levelio import EditorError
from server.editor.properties import COLLISION_MODES

TOOL_LABELS = {"select": "Select", "circle": "Circle", "rectangle": "Rect", "triangle": "Triangle",
               "polygon": "Polygon", "revolute": "Hinge", "fixed": "Weld", "thruster": "Thruster"}
TOOL_OF_LABEL = {label: tool for tool, label in TOOL_LABELS.items()}
# Named by effect, as the play legend names them: the second key of each pair turns the wheel clockwise.
MOTOR_BINDINGS = ("0: ← / → clockwise", "1: ↑ / ↓ clockwise", "2: W / S clockwise", "3: A / D clockwise")
THRUSTER_BINDINGS = ("0: key 1", "1: key 2")


def _plain(text: str) -> str:
    """`text` shown as itself in a markdown widget (a level name or an error can hold *, _, < or [)."""
    return "".join("\\" + c if c in "\\`*_[]<>|" else c for c in text)


class EditorPanel:
    def __init__(self, gui: viser.GuiApi, editor: Editor, on_change: Callable[[], None],
                 send_download: Callable[[str, bytes], None], *, lock: threading.RLock | None = None):
        self.gui, self.editor, self.on_change, self.send_download = gui, editor, on_change, send_download
        self.lock = lock or threading.RLock()
        self._refreshing = False
        self._build()
        self.refresh()

    # ------------------------------------------------------------ plumbing

    def _act(self, action: Callable[[], object]) -> None:
        """Run one editor action from a widget, then refresh the widgets and tell the session."""
        if self._refreshing:
            return
        with self.lock:
            try:
                action()
            except EditorError as error:
                self.editor.notify(str(error))
            self.refresh()
        self.on_change()

    def _button(self, label: str, action: Callable[[], object], hint: str | None = None, **kw):
        button = self.gui.add_button(label, hint=hint, **kw)
        button.on_click(lambda _: self._act(action))
        self.buttons[label] = button
        return button

    def _field(self, handle, name: str, convert=lambda v: v):
        handle.on_update(lambda _: self._act(lambda: self.editor.set_properties(**{name: convert(handle.value)})))
        return handle

    def _param(self, handle, name: str, convert):
        """A level-settings widget: edits go to Editor.set_params, and refresh shows the level's value."""
        handle.on_update(lambda _: self._act(lambda: self.editor.set_params(**{name: convert(handle.value)})))
        self.param_widgets[name] = handle
        return handle

    # ------------------------------------------------------------ widgets

    def _build(self) -> None:
        gui, ed = self.gui, self.editor
        self.buttons: dict[str, viser.GuiButtonHandle] = {}
        self.param_widgets: dict[str, object] = {}
        self.tools = gui.add_button_group("Tool", [TOOL_LABELS[t] for t in TOOLS])
        self.tools.on_click(lambda event: self._act(lambda: ed.set_tool(TOOL_OF_LABEL[event.target.value])))
        self.tool_line = gui.add_markdown("")
        self.message = gui.add_markdown("")
        # Offered with a "no polygon left" refusal (Editor.size_offer): moves the level up one size class, then
        # does the refused edit. Hidden otherwise.
        self.grow_button = self._button("Move to a larger size", ed.grow_size, "the level keeps everything; "
                                        "the next size class has more room", visible=False)
        self.limits_line = gui.add_markdown("")

        with gui.add_folder("Edit"):
            self.undo_button = self._button("Undo", ed.undo, "Ctrl+Z", icon=None)
            self.redo_button = self._button("Redo", ed.redo, "Ctrl+Shift+Z / Ctrl+Y")
            self._button("Delete", ed.delete_selection, "Delete / Backspace")
            self._button("Duplicate", ed.duplicate_selection, "Ctrl+D")
            self._button("Copy", ed.copy, "Ctrl+C")
            self._button("Paste", ed.paste, "Ctrl+V")
            self._button("Rotate +15°", lambda: ed.rotate_selection(15.0), "R, or Alt+drag")
            self._button("Rotate -15°", lambda: ed.rotate_selection(-15.0), "Shift+R")
            self._button("Grow", lambda: ed.scale_selection(1.1), "+, or Ctrl+drag")
            self._button("Shrink", lambda: ed.scale_selection(1 / 1.1), "-")
            self._button("Finish polygon", ed.finish_polygon, "Enter, or click the first vertex")

        with gui.add_folder("Selection"):
            self.summary = gui.add_markdown("Nothing selected.")
            self.role = self._field(gui.add_dropdown("Role", ROLE_NAMES), "role")
            self.fixed = self._field(gui.add_checkbox("Fixed", False), "fixed")
            self.density = self._field(gui.add_number("Density", 1.0, min=0.001, step=0.1), "density")
            self.friction = self._field(gui.add_number("Friction", 1.0, min=0.0, step=0.05), "friction")
            self.restitution = self._field(gui.add_number("Restitution", 0.0, min=0.0, max=1.0, step=0.05),
                                           "restitution")
            self.collision = self._field(gui.add_dropdown("Collides with", COLLISION_MODES, initial_value="normal"),
                                         "collision_mode")
            self.joint_type = self._field(gui.add_dropdown("Joint type", ("revolute", "fixed")), "joint_type")
            self.motor_on = self._field(gui.add_checkbox("Motor on", False), "motor_on")
            self.motor_speed = self._field(gui.add_number("Motor speed", 1.0, step=0.1), "motor_speed")
            self.motor_power = self._field(gui.add_number("Motor power", 1.0, min=0.0, step=0.1), "motor_power")
            self.motor_binding = self._field(gui.add_dropdown("Motor keys", MOTOR_BINDINGS), "motor_binding",
                                             MOTOR_BINDINGS.index)
            self.motor_auto = self._field(gui.add_checkbox("Always driven", False,
                                                           hint="the motor runs at +1 whatever the keys"), "motor_auto")
            self.limits_on = self._field(gui.add_checkbox("Angle limits", False), "limits_on")
            self.limit_min = self._field(gui.add_number("Limit min (°)", -45.0, step=5.0), "limit_min")
            self.limit_max = self._field(gui.add_number("Limit max (°)", 45.0, step=5.0), "limit_max")
            self.thruster_power = self._field(gui.add_number("Thruster power", 1.0, min=0.0, step=0.1),
                                              "thruster_power")
            self.thruster_direction = self._field(gui.add_number("Direction (°)", 90.0, step=15.0),
                                                  "thruster_direction")
            self.thruster_binding = self._field(gui.add_dropdown("Thruster key", THRUSTER_BINDINGS),
                                                "thruster_binding", THRUSTER_BINDINGS.index)
        self.body_widgets = (self.role, self.fixed, self.density, self.friction, self.restitution, self.collision)
        self.joint_widgets = (self.joint_type, self.motor_on, self.motor_speed, self.motor_power, self.motor_binding,
                              self.motor_auto, self.limits_on, self.limit_min, self.limit_max)
        self.thruster_widgets = (self.thruster_power, self.thruster_direction, self.thruster_binding)

        with gui.add_folder("Level"):
            self.gravity = gui.add_vector2("Gravity", tuple(ed.spec.gravity), step=0.1)
            self.gravity.on_update(lambda _: self._act(lambda: ed.set_gravity(*self.gravity.value)))
            self.size = gui.add_dropdown("Size class", tuple(SIZES),
                                         initial_value=ed.size.name if ed.size.name in SIZES else "l")
            self.size.on_update(lambda _: self._act(lambda: ed.set_size(self.size.value)))
            params = ed.properties()["params"]
            self.max_timesteps = self._param(gui.add_number("Time limit (steps)", params["max_timesteps"], min=1,
                                                            max=100_000, step=1, hint="episode length in agent steps"),
                                             "max_timesteps", int)
            self.frame_skip = self._param(gui.add_number("Frame skip", params["frame_skip"], min=1, max=16, step=1,
                                                         hint="physics steps per agent step (a new value compiles "
                                                              "once on the next play)"), "frame_skip", int)
            self.dense_reward_scale = self._param(gui.add_number("Shaping scale", params["dense_reward_scale"],
                                                                 min=0.0, max=10.0, step=0.01,
                                                                 hint="weight of the dense distance reward"),
                                                  "dense_reward_scale", float)
            with gui.add_folder("Physics", expand_by_default=False):
                self.dt = self._param(gui.add_number("Time step (s)", params["dt"], min=0.001, max=0.1, step=0.0001),
                                      "dt", float)
                self.base_motor_speed = self._param(gui.add_number("Motor speed scale", params["base_motor_speed"],
                                                                   min=0.0, step=0.1), "base_motor_speed", float)
                self.base_motor_power = self._param(gui.add_number("Motor power scale", params["base_motor_power"],
                                                                   min=0.0, step=1.0), "base_motor_power", float)
                self.base_thruster_power = self._param(gui.add_number("Thruster power scale",
                                                                      params["base_thruster_power"], min=0.0, step=0.1),
                                                       "base_thruster_power", float)
            self.seed = gui.add_number("Seed", random.randrange(1 << 16), min=0, step=1)
            self._button("New level", lambda: ed.new_level(self.size.value), "walls only, in the chosen size")
            self._button("Shake it up", lambda: ed.shake_it_up(self._next_seed()), "apply random mutators")
            self._button("Random level", lambda: ed.random_level(self._next_seed(), self.size.value))

        with gui.add_folder("Snapping"):
            self.snapping = gui.add_checkbox("Snap", ed.snapping, hint="grid, centres, vertices, edge midpoints")
            self.snapping.on_update(lambda _: self._act(lambda: setattr(ed, "snapping", bool(self.snapping.value))))
            self.grid = gui.add_number("Grid (m)", ed.grid, min=0.0, max=1.0, step=0.05)
            self.grid.on_update(lambda _: self._act(lambda: self._set_grid(self.grid.value)))

        with gui.add_folder("File"):
            self.upload = gui.add_upload_button("Upload level", mime_type="application/json")
            self.upload.on_upload(lambda _: self.upload_file(self.upload.value.name, self.upload.value.content))
            self._button("Download (our format)", lambda: self.download("ours"))
            self._button("Download (Kinetix JSON)", lambda: self.download("kinetix"))
            # What a download did: the file sent, what the public tools do differently with it, or the full reason
            # it cannot be written (in the panel, where a long message has room; not on the canvas).
            self.file_status = gui.add_markdown("")

    def _next_seed(self) -> int:
        seed = int(self.seed.value)
        self.seed.value = seed + 1  # the next press gives another level (refresh is not running: value only)
        return seed

    def _set_grid(self, value: float) -> None:
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
            raise EditorError(f"grid must be >= 0, got {value!r}")
        self.editor.grid = float(value)
        self.editor.notify(None)

    # ------------------------------------------------------------ files

    def upload_file(self, name: str, content: bytes) -> None:
        self._act(lambda: self.editor.import_bytes(content, name))

    def download(self, format: str) -> None:
        label = "the Kinetix format" if format == "kinetix" else "our format"
        with self.lock:
            try:
                text, notes = self.editor.export_with_notes(format)
            except EditorError as error:
                self.file_status.content = f"**Cannot download in {label}:** {_plain(str(error))}"
                return
        name = (self.editor.spec.name or "level").replace("/", "_")
        filename = f"{name}.kinetix.json" if format == "kinetix" else f"{name}.json"
        self.send_download(filename, text.encode())
        # A Kinetix export's first sentence says what it split and the size class it wrote; the rest are notes.
        done = f"Downloaded {_plain(filename)}" + (f": {_plain(notes[0])}." if format == "kinetix" else ".")
        self.file_status.content = "\n\n".join([done] + [f"**Note:** {_plain(note)}" for note in notes[1:]])

    # ------------------------------------------------------------ editor -> widgets

    @contextlib.contextmanager
    def _quiet(self):
        self._refreshing = True
        try:
            yield
        finally:
            self._refreshing = False

    def refresh(self) -> None:
        """Show the editor's current state: tool, selection properties, level settings, limits, message."""
        ed = self.editor
        with self._quiet():
            self.tools.value = TOOL_LABELS[ed.tool]
            self.tool_line.content = f"**Tool:** {ed.tool}" + (" — click vertices, Enter to finish"
                                                                 if ed.tool in ("triangle", "polygon") else "")
            self.message.content = f"⚠ {ed.message}" if ed.message else ""
            self.grow_button.visible = ed.size_offer is not None and ed.message is not None
            if ed.size_offer is not None:
                self.grow_button.label = f"Move to size {ed.size_offer}"
            self.limits_line.content = "**Left:** " + ", ".join(
                f"{capacity - used} {kind}" for kind, (used, capacity) in ed.limits().items())
            self.undo_button.disabled = not ed.can_undo
            self.redo_button.disabled = not ed.can_redo
            props = ed.properties()
            self.gravity.value = tuple(float(g) for g in props["gravity"])
            for name, widget in self.param_widgets.items():
                widget.value = props["params"][name]
            if props["size"] in SIZES:
                self.size.value = props["size"]
            self.snapping.value = ed.snapping
            self.grid.value = ed.grid
            self._show_selection(props)

    def _show_selection(self, props: dict) -> None:
        bodies, joints, thrusters = props["bodies"], props["joints"], props["thrusters"]
        parts = [f"{len(v)} {k}" for k, v in (("bodies", bodies), ("joints", joints), ("thrusters", thrusters)) if v]
        self.summary.content = ("Selected: " + ", ".join(parts) + (" (showing the first of each)" if any(
            len(v) > 1 for v in (bodies, joints, thrusters)) else "")) if parts else "Nothing selected."
        for widgets, items in ((self.body_widgets, bodies), (self.joint_widgets, joints),
                               (self.thruster_widgets, thrusters)):
            for w in widgets:
                w.visible = bool(items)
        if bodies:
            b = bodies[0]
            self.role.value = b["role"]
            self.fixed.value = b["fixed"]
            self.density.value = b["density"]
            self.friction.value = b["friction"]
            self.restitution.value = b["restitution"]
            self.collision.value = COLLISION_MODES[b["collision_mode"]]
        if joints:
            j = joints[0]
            self.joint_type.value = j["joint_type"]
            self.motor_on.value = j["motor_on"]
            self.motor_speed.value = j["motor_speed"]
            self.motor_power.value = j["motor_power"]
            self.motor_binding.value = MOTOR_BINDINGS[j["motor_binding"]]
            self.motor_auto.value = j["motor_auto"]
            self.limits_on.value = j["limits_on"]
            self.limit_min.value = round(j["limit_min"], 3)
            self.limit_max.value = round(j["limit_max"], 3)
            for w in (self.motor_on, self.motor_speed, self.motor_power, self.motor_binding, self.motor_auto,
                      self.limits_on,
                      self.limit_min, self.limit_max):
                w.disabled = j["joint_type"] == "fixed"
        if thrusters:
            t = thrusters[0]
            self.thruster_power.value = t["thruster_power"]
            self.thruster_direction.value = round(t["thruster_direction"], 3)
            self.thruster_binding.value = THRUSTER_BINDINGS[t["thruster_binding"]]
