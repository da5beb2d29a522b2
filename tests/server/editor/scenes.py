"""What the editor-model tests share: a drag gesture and the hinged rectangle-and-wheel scene they edit."""

from __future__ import annotations

from server.editor import Editor


def drag(ed: Editor, a, b, **mods):
    """Press at `a`, move through the midpoint to `b`, release there (one gesture, as a browser sends it)."""
    ed.pointer_down(*a, **mods)
    ed.pointer_move((a[0] + b[0]) / 2, (a[1] + b[1]) / 2, **mods)
    ed.pointer_move(*b, **mods)
    return ed.pointer_up(*b, **mods)


def blank_editor() -> Editor:
    """An empty size-l level with snapping off, so points land exactly where the tests put them."""
    editor = Editor(size="l")
    editor.snapping = False
    return editor


def hinged_editor(*, lone_circle: bool = False) -> Editor:
    """Body 4 a rectangle and body 5 a circle hinged at (1.95, 1.2), a thruster on body 4; with `lone_circle`,
    body 6 is a free circle at (3.5, 3.5). The select tool is on."""
    editor = blank_editor()
    editor.set_tool("rectangle")
    drag(editor, (1.0, 1.0), (2.0, 1.4))
    editor.set_tool("circle")
    drag(editor, (2.0, 1.2), (2.3, 1.2))
    if lone_circle:
        drag(editor, (3.5, 3.5), (3.8, 3.5))
    editor.set_tool("revolute")
    editor.click(1.95, 1.2)
    editor.set_tool("thruster")
    editor.click(1.2, 1.2)
    editor.set_tool("select")
    return editor
