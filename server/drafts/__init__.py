"""Every tab's level and undo history kept on the server as a draft (store) and the tab's part of it (tab)."""
