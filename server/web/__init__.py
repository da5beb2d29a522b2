"""The one port: the side server (page, static files, relay of viser's websocket, /keys) and its web safety."""
