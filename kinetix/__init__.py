"""kinetix: the RL environment, tools and command line built on the jax2d engine."""
