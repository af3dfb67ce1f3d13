"""Checkpoints of a run: which steps a workdir holds, restored on any number of devices."""

import json

import pytest
from conftest import run_python

from gld.runs import checkpoints as checkpoint_lib


def test_the_last_checkpointed_step_counts_only_written_steps(tmp_path):
    assert checkpoint_lib.last_checkpointed_step(tmp_path / "none") == 0
    checkpoints = tmp_path / "checkpoints"
    for name in ("2", "10", "12.orbax-checkpoint-tmp-1700000000", "notes"):
        (checkpoints / name).mkdir(parents=True)
    assert checkpoint_lib.last_checkpointed_step(tmp_path) == 10


CHECKPOINT_SCRIPT = """
import json, sys
import grain, jax, jax.numpy as jnp
from gld import sharding
from gld.runs import checkpoints
from gld.runs.state import TrainState

action, workdir = sys.argv[1:]
scale = 1.0 if action == "save" else 0.0
state = TrainState(
    step=jnp.int32(3), params={"w": scale * jnp.arange(6.0)}, batch_stats={}, opt_state=(),
    rng=jnp.zeros(2, jnp.uint32),
)
state = jax.device_put(state, sharding.replicated(sharding.make_mesh()))
iterator = iter(grain.MapDataset.range(10).to_iter_dataset())
manager = checkpoints.checkpoint_manager(workdir)
if action == "save":
    next(iterator)
    checkpoints.save_checkpoint(manager, state, iterator)
else:  # into an abstract template, as the evaluation and inspection restore
    state = checkpoints.restore_checkpoint(manager, jax.eval_shape(lambda: state), iterator)
print(json.dumps({"w": state.params["w"].tolist(), "next": int(next(iterator))}))
"""


@pytest.mark.parametrize("saved_on, restored_on", [(2, 1), (1, 2)])
def test_a_checkpoint_restores_on_another_number_of_devices(tmp_path, saved_on, restored_on):
    run_python(CHECKPOINT_SCRIPT, "save", str(tmp_path), device_count=saved_on)
    result = run_python(CHECKPOINT_SCRIPT, "restore", str(tmp_path), device_count=restored_on)
    restored = json.loads(result.stdout.strip().splitlines()[-1])
    assert restored == {"w": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0], "next": 1}
