"""Data parallelism, written once: the mesh, batch sharding, and gathering results.

Training and evaluation run on a 1-D `Mesh` of all devices (of all processes) whose
axis `BATCH_AXIS` shards the batch while parameters are replicated; in training on one
process, the train state's large matrices (the baselines' dense layers, and their
optimiser moments) are split over the same axis instead (`state_sharding`). Each
process feeds its own rows (`per_process_batch_size`, `to_global_batch`); results come
back to every host with `gather`. Per-example code that XLA cannot partition by itself
(the `lax.map` filter-bank formulations of `gld.models.filter_banks`) runs on each
device's shard through `on_batch_shards`, which reads the mesh that `under_mesh` sets
around a jitted step.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Sequence
from typing import Any

import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

# Name of the mesh axis that shards the batch.
BATCH_AXIS = "data"


def split_cpu_devices(count: int) -> bool:
    """Makes JAX's CPU backend `count` devices, so that the mesh splits each batch over
    the host's cores (data parallelism). XLA's CPU code runs the per-example filter banks
    of a device on about one core; on the 2-core machine two CPU devices make the main
    job's train step 1.4x faster. Results depend on the device count at the level of
    float rounding (sums over the batch are split), not on the machine.

    Takes effect only before JAX's first operation, and never over a count that
    XLA_FLAGS sets (--xla_force_host_platform_device_count). Returns whether it applied.
    """
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return False
    try:
        jax.config.update("jax_num_cpu_devices", count)
    except RuntimeError:  # JAX has started: its devices stay as they are.
        return False
    return True


def devices_for_batch(batch_size: int, count: int, processes: int = 1) -> int:
    """The largest number of devices per process, at most `count`, over which a global
    batch of `batch_size` rows splits evenly on `processes` processes."""
    for devices in range(count, 0, -1):
        if batch_size % (devices * processes) == 0:
            return devices
    return 1


def make_mesh(devices: Sequence[jax.Device] | None = None) -> Mesh:
    """A 1-D data-parallel mesh over all devices (of all processes)."""
    devices = np.asarray(devices if devices is not None else jax.devices())
    return Mesh(devices, (BATCH_AXIS,))


def replicated(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec())


# Dense layers' train-state arrays of at least this many elements are split over the
# devices (`state_sharding`). The global-local model and Small Enc-Dec have none (their
# largest array has 295K elements), so their steps are the data-parallel ones.
SPLIT_STATE_MIN_SIZE = 1 << 20


def state_sharding(state: Any, mesh: Mesh) -> Any:
    """Where each array of a train state lives during training: the tree of `state` with
    a `NamedSharding` for each leaf.

    A matrix (a dense layer's kernel, and its optimiser moments) of at least
    `SPLIT_STATE_MIN_SIZE` elements is split along its larger axis that the device count
    divides (the first, on a tie); every other array is replicated. Each device then
    holds and updates its part of the layer, and XLA's partitioner computes the layer
    split: at batch 16 its matmul is bound by reading the kernel. On the 2-core CPU,
    Eigen's train step at 128x96 (19.7M parameters, 15.7M of them in two dense layers)
    takes 0.63-0.69 s against 1.00-1.06 replicated, its loss equal to float rounding.
    Conv kernels stay replicated: split too, FCRN's step was 6-12% slower (DispNet's 10%
    faster). Over several processes everything stays replicated: each process reads the
    whole state back (checkpoints, evaluation), which a split one would not let it do.
    """
    count = mesh.shape[BATCH_AXIS]

    def place(leaf: Any) -> NamedSharding:
        shape = getattr(leaf, "shape", ())
        if (
            count == 1
            or jax.process_count() > 1
            or len(shape) != 2
            or math.prod(shape) < SPLIT_STATE_MIN_SIZE
        ):
            return replicated(mesh)
        axes = [axis for axis, size in enumerate(shape) if size % count == 0]
        if not axes:
            return replicated(mesh)
        split = max(axes, key=lambda axis: (shape[axis], -axis))
        spec = [None] * len(shape)
        spec[split] = BATCH_AXIS
        return NamedSharding(mesh, PartitionSpec(*spec))

    return jax.tree_util.tree_map(place, state)


def batch_sharded(mesh: Mesh) -> NamedSharding:
    return NamedSharding(mesh, PartitionSpec(BATCH_AXIS))


def to_global_batch(local_batch: dict[str, np.ndarray], mesh: Mesh, keys: Sequence[str]) -> dict:
    """This process's rows -> global arrays sharded on the batch axis."""
    sharding = batch_sharded(mesh)
    return {
        key: jax.make_array_from_process_local_data(sharding, np.asarray(local_batch[key]))
        for key in keys
    }


def per_process_batch_size(global_batch_size: int, mesh: Mesh) -> int:
    """Rows each process feeds; the global batch must split evenly over devices."""
    if global_batch_size % mesh.devices.size:
        raise ValueError(
            f"batch_size {global_batch_size} is not divisible by the {mesh.devices.size} devices"
        )
    return global_batch_size // jax.process_count()


def evaluation_batch_size(batch_size: int, mesh: Mesh) -> int:
    """`batch_size` rounded up to a multiple of the devices: evaluation batches are padded
    (padded rows are masked), so any requested size works on any number of devices."""
    devices = mesh.devices.size
    return -(-batch_size // devices) * devices


def under_mesh(jitted: Callable, mesh: Mesh) -> Callable:
    """Calls (and so traces) `jitted` with `mesh` set, so that `on_batch_shards` finds
    the mesh's batch axis."""

    @functools.wraps(jitted)
    def call(*args):
        with jax.set_mesh(mesh):
            return jitted(*args)

    return call


def gather(tree: Any) -> Any:
    """Fully materialise a (possibly multi-process) sharded pytree as numpy on every host."""
    if jax.process_count() == 1:
        return jax.tree_util.tree_map(np.asarray, tree)
    from jax.experimental import multihost_utils

    return multihost_utils.process_allgather(tree, tiled=True)


def _utf8_prefix(text: str, max_bytes: int) -> bytes:
    """At most `max_bytes` of `text`'s UTF-8 encoding, never half a character."""
    return text.encode()[:max_bytes].decode(errors="ignore").encode()


def gather_strings(values: Sequence[Any], max_bytes: int = 120) -> list[str]:
    """Every process's strings (e.g. example ids, at most `max_bytes` of UTF-8 each, cut
    between characters), in process order, on every host."""
    if jax.process_count() == 1:
        return [str(value) for value in values]
    from jax.experimental import multihost_utils

    encoded = np.array(
        [list(_utf8_prefix(str(value), max_bytes).ljust(max_bytes, b"\0")) for value in values],
        np.uint8,
    )
    gathered = multihost_utils.process_allgather(encoded, tiled=True)
    return [bytes(row).rstrip(b"\0").decode() for row in np.asarray(gathered)]


def on_batch_shards(
    apply: Callable, batch_size: int, *, replicated: tuple[int, ...] = ()
) -> Callable:
    """`apply(*args)`, a function of each example alone, run on each device's shard of
    the batch.

    XLA's partitioner cannot split a `lax.map` over its mapped axis: given a batch
    sharded over devices, it gathers the whole batch on every device and each device
    loops over all examples; and it may reshard a computation per example between its
    steps (an all-to-all each time). When a mesh with a `BATCH_AXIS` axis is set
    (`jax.set_mesh`, as `under_mesh` does around the jitted steps) and divides the batch,
    `shard_map` gives each device its own examples: every argument (a pytree) is split on
    its leading batch axis, except those at the positions `replicated` (e.g. a kernel
    shared by the batch; its gradient is summed over devices). The outputs are split on
    their batch axis too.
    """
    mesh = jax.sharding.get_abstract_mesh()
    if mesh.empty or BATCH_AXIS not in mesh.axis_names:
        return apply
    devices = mesh.shape[BATCH_AXIS]
    if devices == 1 or batch_size % devices:
        return apply
    batch = PartitionSpec(BATCH_AXIS)
    explicit = mesh.axis_types[mesh.axis_names.index(BATCH_AXIS)] == jax.sharding.AxisType.Explicit

    def sharded(*args):
        specs = tuple(PartitionSpec() if i in replicated else batch for i in range(len(args)))
        if explicit:
            # Explicit sharding: the arguments' types must already carry the specs.
            args = tuple(jax.reshard(arg, spec) for arg, spec in zip(args, specs, strict=True))
        mapped = jax.shard_map(apply, mesh=mesh, in_specs=specs, out_specs=batch, check_vma=False)
        return mapped(*args)

    return sharded
