"""The web application: editor, play loop, agents, recordings and gallery served to the browser (docs/server.md)."""
