"""The browser level editor's model: pure Python over `kinetix.formats.LevelSpec` (viser only in panel.py)."""

from server.editor.editor import TOOLS, Editor, Overlay
from server.editor.levelio import EditorError

__all__ = ["Editor", "EditorError", "Overlay", "TOOLS"]
