"""The gallery's storage and API: levels, votes, plays, best runs, agents, rate limits. Nothing here draws or
drives a session (the tab's part is server/play/gallery_tab.py)."""
