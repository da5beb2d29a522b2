"""Training over several processes and hosts on JAX's own distributed runtime (jax.distributed).

Every process runs the same `kinetix train` command (multi-controller SPMD). `initialize` connects it to the
coordinator before JAX starts its backend; from then on `jax.devices()` lists the devices of every process, the
trainer's mesh spans them all, and each process steps only its own shard of the environments while XLA
all-reduces the gradients across processes (on CPU through gloo, JAX's default CPU collectives since 0.4.3x;
checked in jax/_src/config.py of the pinned 0.10: `jax_cpu_collectives_implementation` defaults to "gloo").

Decisions that end or checkpoint a run are made by process 0 and broadcast (`agree`), so no process leaves a
collective the others are waiting in; only process 0 writes files (`is_main`).
"""

from __future__ import annotations

import warnings

import numpy as np

MEET_TIMEOUT_S = 3600.0  # how long processes wait for each other's compile (a cold l-size compile takes minutes)
_meetings = 0  # barriers passed: each needs a name of its own, the same in every process


class MultihostError(ValueError):
    """Bad multi-host settings (a clear message for the command line)."""


def parse_coordinator(text: str) -> str:
    """Check HOST:PORT (IPv6 hosts in brackets) and return it unchanged."""
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise MultihostError(f"--coordinator must be HOST:PORT with a port in 1-65535, got {text!r}")
    return text


def detected_cluster() -> str | None:
    """The cluster environment jax.distributed.initialize() would detect by itself (SLURM, Open MPI, Kubernetes
    JobSets, Cloud TPU), when it reports more than one process; None otherwise (a plain single-process run).

    Reads JAX's own detectors (jax._src.clusters, internal API of the pinned JAX), so it agrees with what
    initialize() does; mpi4py detection is opt-in in JAX and therefore not automatic here either."""
    try:
        from jax._src import clusters

        candidates = [env for env in clusters.ClusterEnv._cluster_types if not env.opt_in_only_method]
    except (ImportError, AttributeError):
        return None
    for env in candidates:
        try:
            # quietly: JAX's Kubernetes detector warns in any pod without the `kubernetes` package
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if env.is_env_present() and int(env.get_process_count()) > 1:
                    return env.__name__
        except Exception:  # a detector that cannot answer here (missing variables, no metadata server)
            continue
    return None


def initialize(coordinator: str | None = None, num_processes: int | None = None,
               process_id: int | None = None) -> bool:
    """Join the distributed runtime before any JAX computation. Returns True when this is a multi-process run.

    With all three arguments: that coordinator, process count and index. With none: whatever cluster JAX
    detects (see `detected_cluster`), else a single process. Anything in between is a MultihostError."""
    given = [value is not None for value in (coordinator, num_processes, process_id)]
    if any(given) and not all(given):
        raise MultihostError("multi-host training needs all of --coordinator HOST:PORT, --num-processes N and "
                             "--process-id I (or none of them, to use the cluster environment JAX detects)")
    import jax

    if all(given):
        parse_coordinator(coordinator)
        if num_processes < 1 or not 0 <= process_id < num_processes:
            raise MultihostError(f"--process-id must be in 0..{num_processes - 1} for --num-processes "
                                 f"{num_processes}, got {process_id}")
        if num_processes == 1:
            return False
        jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                                   process_id=process_id)
        return True
    if detected_cluster() is None:
        return False
    jax.distributed.initialize()
    return jax.process_count() > 1


def compile_together(jitted, *args, timeout_s: float = MEET_TIMEOUT_S) -> None:
    """Compile `jitted` for `args` now (the later call reuses it), then wait until every process has done so.

    A collective gives the processes 30 s to join it (gloo's connect: "Gloo context initialization failed:
    ... GetKeyValue() timed out ... 29.99999993s"), and a call's compile happens inside the call. Two processes
    compiling the l-size PPO update (levels/cartpole.json, defaults) on a loaded 2-core machine finished more than
    30 s apart, and the first update's gradient all-reduce killed the run. The coordination service's barrier
    waits as long as `timeout_s`. A no-op in a single process."""
    import jax

    if jax.process_count() == 1:
        return
    jitted.lower(*args).compile()
    from jax._src import distributed  # the runtime's own client (JAX has no public barrier without a collective)

    global _meetings
    _meetings += 1
    distributed.global_state.client.wait_at_barrier(f"kinetix-compiled-{_meetings}", int(timeout_s * 1000))


def is_main() -> bool:
    """True in the process that writes files and shows progress (process 0; the only one when not distributed)."""
    import jax

    return jax.process_index() == 0


def agree(*flags: bool) -> tuple[bool, ...]:
    """Process 0's flags, on every process (a small collective); the flags themselves when single-process."""
    import jax

    if jax.process_count() == 1:
        return tuple(bool(f) for f in flags)
    from jax.experimental import multihost_utils

    values = multihost_utils.broadcast_one_to_all(np.asarray(flags, np.int32))
    return tuple(bool(v) for v in np.asarray(values))
