"""Benchmarks behind `kinetix bench ...`: `engine` measures the jax2d step on fixed scenes (see scenes.py)."""
