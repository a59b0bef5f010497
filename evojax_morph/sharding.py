"""Split a batch of morphologies across every device (and host) with JAX's own sharding.

The fitness of one morphology never talks to another's, so a batch splits across devices with
no communication: `shard_batch` places the batch axis of a function's inputs and outputs on a
one-axis `Mesh` ("batch") with `NamedSharding`, padding the batch to a multiple of the device
count and cutting the padding off the result. On one device it returns the function unchanged.

Multi-host: call `init_distributed()` first in every process (the CLI's --distributed); then
`jax.devices()` lists every host's devices, `batch_mesh()` spans them all, and every process
runs the same program on the same arguments (SPMD).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "batch"


@functools.cache
def _mesh(devices: tuple) -> Mesh:
    return Mesh(np.array(devices), (AXIS,))


def batch_mesh(devices=None) -> Mesh:
    """A one-axis mesh ("batch") over `devices` (default: every device of every process)."""
    return _mesh(tuple(jax.devices() if devices is None else devices))


def replicated(mesh: Mesh) -> NamedSharding:
    """Every device holds the whole array: for agent state and anything a host reads back."""
    return NamedSharding(mesh, PartitionSpec())


def shard_batch(fn: Callable, mesh: Mesh | None = None, manual: bool = False) -> Callable:
    """`fn` with the leading (batch) axis of every argument and output split across `mesh`.

    Args:
      fn: maps pytrees of arrays with a common leading axis B to pytrees with leading axis B,
        each element independent of the others (a vmapped per-morphology function).
      mesh: a one-axis mesh from `batch_mesh`; default: all devices. With one device `fn` is
        returned unchanged.
      manual: split with `jax.shard_map` (each device runs `fn` on its own B / n elements) rather
        than by XLA's partitioner: for a `fn` that calls a foreign function (MuJoCo Warp's FFI
        call), which the partitioner cannot split and runs whole on every device.
    Returns:
      A function of the same signature, for use inside `jax.jit`. B need not divide the device
      count: the batch is padded with copies of its first element, whose results are dropped.

    Without `manual` the split is a sharding constraint on the inputs and outputs, which XLA's
    partitioner carries through `fn`. Each device computes its own elements; the one
    communication left is a one-flag all-reduce per iteration of MJX's solver loop (a vmapped
    while loop runs until every element converged, on every device), so results equal one
    device's up to rounding. `jax.shard_map` would drop that flag, but MJX's JAX step under
    shard_map crashed XLA's CUDA plugin on 2 GPUs (jax 0.11.2; see docs/benchmarks.md), so the
    JAX engine keeps the constraints and Warp, which needs it, takes shard_map.
    """
    mesh = batch_mesh() if mesh is None else mesh
    if mesh.size == 1:
        return fn
    split = NamedSharding(mesh, PartitionSpec(AXIS))
    constrain = lambda tree: jax.tree.map(
        lambda x: jax.lax.with_sharding_constraint(x, split), tree
    )
    if manual:  # each argument and output split on its leading axis
        # `fn` jitted on its own inside the shard_map: unjitted, MuJoCo Warp's call in it
        # segfaults jax 0.11.2's Shardy (ManualComputationUnusedInputsPattern); jitted, it
        # compiles with jax 0.10.2, 0.11.2 and 0.12 (CPU, 2026-11-28), and with 0.11.2 on 2 and 4
        # GPUs steps each device's share as a lone GPU would (docs/benchmarks.md "The Warp fitness
        # across GPUs").
        body = jax.shard_map(jax.jit(fn), mesh=mesh, in_specs=PartitionSpec(AXIS),
                             out_specs=PartitionSpec(AXIS), check_vma=False)
    else:
        body = lambda *args: constrain(fn(*constrain(args)))  # noqa: E731

    def wrapped(*args):
        batch = jax.tree.leaves(args)[0].shape[0]
        pad = -batch % mesh.size
        if pad:
            args = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[:1], pad, 0)]), args)
        out = body(*args)
        return jax.tree.map(lambda x: x[:batch], out) if pad else out

    return wrapped


def jit_replicated(init: Callable, chunk: Callable, mesh: Mesh | None = None):
    """An agent's `init(key)` and `chunk(state, num_steps)` jitted with every output replicated
    on `mesh` (default: all devices): the agent is small, the fitness inside splits its batch
    across the devices, and a state whose placement never changes compiles once."""
    everywhere = replicated(batch_mesh() if mesh is None else mesh)
    return jax.jit(init, out_shardings=everywhere), jax.jit(
        chunk, static_argnums=1, out_shardings=everywhere
    )


def to_host(tree):
    """Numpy copies of a pytree of arrays, also when they are spread over several processes."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        tree = multihost_utils.process_allgather(tree, tiled=True)
    return jax.device_get(tree)


def barrier(name: str) -> None:
    """Every process waits here for the others (nothing to do with one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)


def broadcast_json(value):
    """Process 0's `value` (JSON-able) on every process: itself with one process."""
    if jax.process_count() == 1:
        return value
    import json

    from jax.experimental import multihost_utils

    data = np.frombuffer(json.dumps(value).encode(), np.uint8)
    size = multihost_utils.broadcast_one_to_all(np.int64(len(data)))
    data = np.resize(data, int(size))  # the others' padding, overwritten
    return json.loads(bytes(multihost_utils.broadcast_one_to_all(data)).decode())


def init_distributed(
    coordinator: str | None = None, num_processes: int | None = None, process_id: int | None = None
):
    """`jax.distributed.initialize`: with no arguments JAX detects SLURM (or another cluster);
    otherwise pass the coordinator's "host:port", the number of processes and this one's id."""
    jax.distributed.initialize(
        coordinator_address=coordinator, num_processes=num_processes, process_id=process_id
    )
