"""Data parallelism: the mesh, per-process batches, global arrays and gathering."""

import jax
import numpy as np
import pytest
from jax.sharding import PartitionSpec

from gld import sharding


def test_a_local_batch_becomes_a_global_array_sharded_on_the_batch_axis():
    mesh = sharding.make_mesh()
    batch = {"x": np.arange(12, dtype=np.float32).reshape(4, 3), "id": np.array(list("abcd"))}
    global_batch = sharding.to_global_batch(batch, mesh, ["x"])
    assert set(global_batch) == {"x"}  # host-only keys stay on the host
    assert global_batch["x"].sharding.spec == PartitionSpec(sharding.BATCH_AXIS)
    np.testing.assert_array_equal(sharding.gather(global_batch)["x"], batch["x"])


def test_the_global_batch_must_split_over_the_devices():
    mesh = sharding.make_mesh()
    devices = mesh.devices.size
    assert sharding.per_process_batch_size(4 * devices, mesh) == 4 * devices
    if devices > 1:
        with pytest.raises(ValueError, match="not divisible"):
            sharding.per_process_batch_size(devices + 1, mesh)


def test_ids_come_back_as_strings_in_order():
    assert sharding.gather_strings(np.array(["a/1", "b/2"])) == ["a/1", "b/2"]


def test_without_a_mesh_per_example_code_runs_unsharded():
    apply = lambda banks, inputs, head: inputs  # noqa: E731
    assert sharding.on_batch_shards(apply, 8) is apply
    mesh = sharding.make_mesh(jax.devices()[:1])
    with jax.set_mesh(mesh):
        # one device: nothing to split
        assert sharding.on_batch_shards(apply, 8) is apply


def test_an_evaluation_batch_is_rounded_up_to_the_devices():
    class ThreeDevices:
        devices = np.empty(3, object)

    assert [sharding.evaluation_batch_size(n, ThreeDevices) for n in (1, 3, 16, 18)] == [
        3,
        3,
        18,
        18,
    ]
