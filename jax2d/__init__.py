"""jax2d: a 2D rigid-body physics engine in JAX."""
