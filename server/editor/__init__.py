"""The browser level editor's model: pure Python over `kinetix.formats.LevelSpec` (viser only in panel.py).

Modules, one concept each:
- editor.py: `Editor` (the document: level, size class, tool, selection, history, overlay) and `Overlay`.
- selection.py: hit tests, joint assemblies, move/rotate/scale, delete, copy/paste on a spec.
- properties.py: the panel's fields of bodies, joints and thrusters, and applying edits to them.
- snapping.py: snapping to vertices, body centres, edge midpoints, alignment and the grid, with guide lines.
- history.py: bounded undo/redo of level snapshots.
- levelio.py: import (either format) and export, new / random / shaken levels, `EditorError`.
- geometry.py: plane geometry of bodies in world coordinates.
- panel.py: `EditorPanel`, the edit-mode viser GUI.

Decisions:
- Select tool: drag moves, Alt+drag rotates, Ctrl+drag resizes (each one undo step); R / Shift+R turn 15°,
  + / - resize by 10%.
- The 4 standard walls cannot be selected, moved or deleted (they are what the Kinetix format and the
  generators expect in polygon slots 0-3); they can be the other end of a joint, to pin a body to the world.
- Pointer input: `pointer_down` / `pointer_move` / `pointer_up` describe one gesture; a press and release
  less than 2 cm apart is a click and `pointer_up` handles it as `click` would. Call either `click` or
  the down/up pair for one gesture, never both.
- A click with the circle or rectangle tool (no drag) makes a shape of a default size (r 0.2 m, 0.4 m side).
- Angles the user sees are degrees (joint limits, thruster direction in the world frame); specs keep radians.
- `limits()` counts the walls among the polygons, as the size classes do.
- Moving, rotating or resizing a body moves its whole joint assembly (never the walls); joints to the
  walls stay closed (the wall-side anchor follows), and rotating updates their reference angle.
"""

from server.editor.editor import TOOLS, Editor, Overlay
from server.editor.levelio import EditorError, warm_up

__all__ = ["Editor", "EditorError", "Overlay", "TOOLS", "warm_up"]
