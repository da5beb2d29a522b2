"""The web application: editor, play loop and gallery served to the browser (planned)."""
