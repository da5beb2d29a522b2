"""Spreading training over all local devices with jax.sharding.

The env batch (every array whose leading axis is num_envs) is split over a 1-D mesh axis "batch"; network
parameters and optimiser state stay replicated. Nothing else changes: jit follows the data, so the rollout runs
data-parallel and XLA's SPMD partitioner turns the minibatch gradient means into cross-device all-reduces. The
numbers are those of the single-device program up to float summation order (tests/kinetix/agents/test_sharding.py).
"""

from __future__ import annotations

from typing import Any

import jax
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from kinetix.devices import BATCH_AXIS, local_mesh

__all__ = ["batch_sharder", "local_mesh"]


def batch_sharder(mesh: Mesh, batch_size: int):
    """`shard(tree)`: constrain every array whose leading axis is `batch_size` to be split over the mesh.

    Works on concrete arrays and inside jit. batch_size must be divisible by the device count."""
    count = mesh.devices.size
    if batch_size % count:
        raise ValueError(f"num_envs ({batch_size}) must be divisible by the number of devices ({count})")
    split = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))

    def shard(tree: Any) -> Any:
        def one(x):
            if getattr(x, "ndim", 0) >= 1 and x.shape[0] == batch_size:
                return jax.lax.with_sharding_constraint(x, split)
            return x

        return jax.tree.map(one, tree)

    return shard
