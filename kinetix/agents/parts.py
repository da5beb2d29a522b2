"""The network over a large batch in cache-sized parts on the CPU: forward passes and accumulated gradients.

On the CPU the cost per sample of the entity network grows with the batch once its activations leave the cache
(each is batch x tokens x width floats). Measured on the 2-core development machine (AMD EPYC, loaded by other
jobs, so only the ratios hold; size s, entity network of width 64), milliseconds per pass:

| batch | forward | forward + backward |
|---:|---:|---:|
| 256 | 1.7-2.0 | 7-22 |
| 2,048 | 16-18 | 420-600 |
| 8,192 | 470-550 | 2,470-2,670 |

A PPO minibatch of 8,192 samples (512 envs x 64 steps / 4) therefore costs several times as much in one pass as in
parts of 256. So on the CPU, `forward` maps the network over parts of `CPU_PART` samples one after the other
(lax.map) and `mean_grad` accumulates the gradient of a mean loss over such parts (lax.scan): the same numbers as
one pass up to float summation order. On other backends (a GPU wants the whole batch at once) both are one pass,
as jax2d.step_batch does for the physics.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax
import jax.numpy as jnp

from jax2d import compiling

CPU_PART = 256  # samples per pass on the CPU (see the table above)


def _parts(batch: int) -> int:
    """How many equal parts of at most CPU_PART a batch splits into (1 when no equal split exists)."""
    count = -(-batch // CPU_PART)
    while count < batch and batch % count:
        count += 1
    return count if batch % count == 0 and count > 1 else 1


def _split(tree: Any, count: int) -> Any:
    """(B, ...) -> (count, B / count, ...) with part c holding rows c, c + count, c + 2 count, ...: when the batch axis
    is split over devices (kinetix.agents.sharding), every part is then split the same way, and the loop over the
    parts needs no data from another device."""
    return jax.tree.map(lambda x: jnp.moveaxis(x.reshape((x.shape[0] // count, count) + x.shape[1:]), 1, 0), tree)


def _join(tree: Any) -> Any:
    """The inverse of _split."""
    return jax.tree.map(lambda x: jnp.moveaxis(x, 0, 1).reshape((x.shape[0] * x.shape[1],) + x.shape[2:]), tree)


def by_platform(cpu: Callable, whole: Callable, *args: Any) -> Any:
    """`cpu(*args)` on the CPU, `whole(*args)` elsewhere: decided at trace time on a one-backend machine, else by
    the platform the program is lowered for (lax.platform_dependent)."""
    only = compiling.only_platform()
    if only is not None:
        return (cpu if only == "cpu" else whole)(*args)
    return jax.lax.platform_dependent(*args, cpu=cpu, default=whole)


def forward(apply: Callable[[Any], Any], batch: Any) -> Any:
    """`apply(batch)` for a function of a batch (leading axis) whose outputs are batched the same way."""
    count = _parts(jax.tree.leaves(batch)[0].shape[0])
    if count == 1:
        return apply(batch)
    return by_platform(lambda b: _join(jax.lax.map(apply, _split(b, count))), apply, batch)


def mean_grad(loss: Callable[..., tuple[jax.Array, Any]], params: Any, batch: Any) -> tuple[Any, Any]:
    """(aux, grads) of `loss(params, batch) -> (scalar, aux)`, a MEAN over the batch's samples.

    In parts, the loss and aux of each part are averaged over the parts and so are the gradients: equal parts make
    that the whole batch's mean. Every aux leaf must itself be a mean over the samples."""
    grad_fn = jax.value_and_grad(loss, has_aux=True)
    count = _parts(jax.tree.leaves(batch)[0].shape[0])

    def whole(p, b):
        (_, aux), grads = grad_fn(p, b)
        return aux, grads

    if count == 1:
        return whole(params, batch)

    def in_parts(p, b):
        def one(total, part):
            aux, grads = whole(p, part)
            return jax.tree.map(jnp.add, total, (aux, grads)), None

        shapes = jax.eval_shape(whole, p, jax.tree.map(lambda x: x[: x.shape[0] // count], b))
        zeros = jax.tree.map(lambda s: jnp.zeros(s.shape, s.dtype), shapes)
        total, _ = jax.lax.scan(one, zeros, _split(b, count))
        return jax.tree.map(lambda x: x / count, total)

    return by_platform(in_parts, whole, params, batch)
