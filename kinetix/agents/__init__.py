"""Agents: PPO training (kinetix.agents.ppo), curricula, checkpoints, evaluation and `load_policy`."""
