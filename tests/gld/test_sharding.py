"""Data parallelism: the mesh, per-process batches, global arrays and gathering."""

import json

import jax
import jax.numpy as jnp
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


class _Devices:
    """A mesh's device array, as far as the batch-size functions read it."""

    def __init__(self, count):
        self.devices = np.empty(count, object)


@pytest.mark.parametrize("processes, devices_per_process", [(1, 1), (1, 4), (2, 2), (4, 3)])
def test_each_process_feeds_its_share_of_a_batch_that_splits_over_all_devices(
    monkeypatch, processes, devices_per_process
):
    monkeypatch.setattr(jax, "process_count", lambda: processes)
    mesh = _Devices(processes * devices_per_process)
    for global_batch in range(1, 4 * processes * devices_per_process + 1):
        if global_batch % (processes * devices_per_process):
            with pytest.raises(ValueError, match="not divisible"):
                sharding.per_process_batch_size(global_batch, mesh)
            continue
        local = sharding.per_process_batch_size(global_batch, mesh)
        # The processes' rows make the global batch, and each process's rows split
        # evenly over its own devices.
        assert local * processes == global_batch
        assert local % devices_per_process == 0


def test_ids_of_every_process_come_back_as_strings_in_process_order(monkeypatch):
    from jax.experimental import multihost_utils

    # Three simulated processes: each encodes its own ids; the all-gather stacks what
    # they sent, in process order.
    ids = [
        np.array(["scenes/0", "scenes/3"]),
        np.array(["b/é", "x" * 200, "a" + "é" * 60]),
        np.array([7, 8]),
    ]
    sent = []
    monkeypatch.setattr(jax, "process_count", lambda: len(ids))

    def record(encoded, tiled):
        sent.append(encoded)
        return encoded

    monkeypatch.setattr(multihost_utils, "process_allgather", record)
    for values in ids:
        sharding.gather_strings(values)
    monkeypatch.setattr(
        multihost_utils, "process_allgather", lambda encoded, tiled: np.concatenate(sent)
    )
    gathered = sharding.gather_strings(ids[0])
    # Every string up to max_bytes (120) of its UTF-8 encoding, cut between characters.
    assert gathered == ["scenes/0", "scenes/3", "b/é", "x" * 120, "a" + "é" * 59, "7", "8"]
    monkeypatch.setattr(jax, "process_count", lambda: 1)
    assert sharding.gather_strings(np.array([3, 4])) == ["3", "4"]


def test_per_example_code_runs_on_each_devices_share_of_the_batch():
    from jax.sharding import AbstractMesh

    seen = []

    def apply(banks, inputs, head):
        seen.append((banks.shape, inputs.shape, head.shape))
        return inputs * head.sum()

    def shapes_seen(batch_size, devices):
        seen.clear()
        mesh = AbstractMesh((devices,), (sharding.BATCH_AXIS,))
        with jax.sharding.use_abstract_mesh(mesh):
            jaxpr = jax.make_jaxpr(sharding.on_batch_shards(apply, batch_size, replicated=(2,)))(
                jnp.zeros((batch_size, 3)), jnp.zeros((batch_size, 2)), jnp.zeros(5)
            )
        assert jaxpr.out_avals[0].shape == (batch_size, 2)  # the whole batch comes back
        return seen

    # Four devices, eight examples: each device two; the shared head whole on every one.
    assert shapes_seen(8, 4) == [((2, 3), (2, 2), (5,))]
    # A batch the devices do not divide, or one device: the whole batch in one call.
    assert shapes_seen(6, 4) == [((6, 3), (6, 2), (5,))]
    assert shapes_seen(8, 1) == [((8, 3), (8, 2), (5,))]
    # No mesh at all.
    seen.clear()
    jax.make_jaxpr(sharding.on_batch_shards(apply, 8, replicated=(2,)))(
        jnp.zeros((8, 3)), jnp.zeros((8, 2)), jnp.zeros(5)
    )
    assert seen == [((8, 3), (8, 2), (5,))]


def test_every_argument_is_split_unless_replicated():
    from jax.sharding import AbstractMesh

    seen = []

    def apply(pair, scale):
        seen.append((pair[0].shape, pair[1].shape, scale.shape))
        return pair[0] * scale, pair[1]

    mesh = AbstractMesh((2,), (sharding.BATCH_AXIS,))
    with jax.sharding.use_abstract_mesh(mesh):
        jaxpr = jax.make_jaxpr(sharding.on_batch_shards(apply, 4))(
            (jnp.zeros((4, 3)), jnp.zeros((4, 5, 2))), jnp.zeros((4, 1))
        )
    # A pytree's leaves and every other argument split on the batch axis; the outputs too.
    assert seen == [((2, 3), (2, 5, 2), (2, 1))]
    assert [aval.shape for aval in jaxpr.out_avals] == [(4, 3), (4, 5, 2)]


def test_large_matrices_of_the_state_are_split_along_their_larger_divisible_axis(monkeypatch):
    from jax.sharding import AbstractMesh

    large = sharding.SPLIT_STATE_MIN_SIZE
    state = {
        "dense": jax.ShapeDtypeStruct((large // 2, 4), np.float32),
        "columns": jax.ShapeDtypeStruct((6, large), np.float32),
        "conv": jax.ShapeDtypeStruct((3, 3, 64, large // 64), np.float32),
        "tie": jax.ShapeDtypeStruct((1024, 1024), np.float32),
        "indivisible": jax.ShapeDtypeStruct((large + 1,), np.float32),
        "small": jax.ShapeDtypeStruct((large // 4, 2), np.float32),
        "step": np.int32(0),
    }
    specs = jax.tree_util.tree_map(
        lambda placed: placed.spec,
        sharding.state_sharding(state, AbstractMesh((4,), (sharding.BATCH_AXIS,))),
    )
    axis = sharding.BATCH_AXIS
    assert specs == {
        "dense": PartitionSpec(axis, None),
        "columns": PartitionSpec(None, axis),
        "conv": PartitionSpec(),  # conv kernels stay whole
        "tie": PartitionSpec(axis, None),
        "indivisible": PartitionSpec(),
        "small": PartitionSpec(),
        "step": PartitionSpec(),
    }
    # One device, or several processes (each reads the whole state back): replicated.
    for count, processes in ((1, 1), (4, 2)):
        monkeypatch.setattr(jax, "process_count", lambda processes=processes: processes)
        mesh = AbstractMesh((count,), (sharding.BATCH_AXIS,))
        placed = sharding.state_sharding(state, mesh)
        assert all(leaf.spec == PartitionSpec() for leaf in jax.tree_util.tree_leaves(placed))


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
