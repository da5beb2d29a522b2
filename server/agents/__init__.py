"""Agents in a browser tab: Watch agent and Race the agent (play), the tab's Agents panel, training runs in worker
processes."""
