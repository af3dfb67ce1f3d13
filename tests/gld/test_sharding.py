"""Data parallelism: the mesh, per-process batches, global arrays and gathering."""

import json

import jax
import numpy as np
import pytest
from conftest import _interpreter, run_python
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


def test_the_devices_for_a_batch_divide_it():
    assert sharding.devices_for_batch(16, 2) == 2
    assert sharding.devices_for_batch(3, 2) == 1
    assert sharding.devices_for_batch(12, 8) == 6
    # Over processes: each process's share must split over its devices.
    assert sharding.devices_for_batch(8, 4, processes=2) == 4
    assert sharding.devices_for_batch(6, 4, processes=2) == 3
    assert sharding.devices_for_batch(5, 4, processes=2) == 1


SPLIT_SCRIPT = """
import json, os, sys
from gld import sharding
applied = sharding.split_cpu_devices(int(sys.argv[1]))
import jax
count = len(jax.devices())
late = sharding.split_cpu_devices(5)
print(json.dumps({"applied": applied, "count": count, "late": late, "after": len(jax.devices())}))
"""


def test_the_cpu_is_split_before_jax_starts_and_never_over_xla_flags():
    env = {"XLA_FLAGS": ""}
    result = _interpreter(["-c", SPLIT_SCRIPT, "2"], timeout=120, env=env)
    assert result.returncode == 0, result.stderr[-2000:]
    split = json.loads(result.stdout.strip().splitlines()[-1])
    # Once JAX has started, its devices stay as they are.
    assert split == {"applied": True, "count": 2, "late": False, "after": 2}
    # A device count in XLA_FLAGS wins.
    forced = json.loads(run_python(SPLIT_SCRIPT, "2", device_count=3).stdout.splitlines()[-1])
    assert forced == {"applied": False, "count": 3, "late": False, "after": 3}
    with pytest.raises(ValueError, match="count must be >= 1"):
        sharding.split_cpu_devices(0)
