"""Checkpoints of a run: which steps a workdir holds, restored on any number of devices."""

import errno
import json
import logging
import os

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


COMPILES_SCRIPT = """
import json, sys
import grain, jax, numpy as np, optax
from gld import sharding
from gld.runs import checkpoints, state as state_lib

compiles = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **_: compiles.append(event)
    if event == "/jax/core/compile/backend_compile_duration" else None
)
# Six shapes, Adam's state beside them.
params = {f"w{i}": jax.random.normal(jax.random.key(i), (2 * i + 2, 8)) for i in range(6)}
state = state_lib.state_of({"params": params}, optax.adam(1e-3), seed=0)
state = jax.device_put(state, sharding.replicated(sharding.make_mesh()))
manager = checkpoints.checkpoint_manager(sys.argv[1])
iterator = iter(grain.MapDataset.range(10).to_iter_dataset())
before = len(compiles)
checkpoints.save_checkpoint(manager, state, iterator)
saved = len(compiles) - before
restored = checkpoints.restore_checkpoint(manager, jax.eval_shape(lambda: state), iterator)
same = all(
    np.array_equal(a, b) for a, b in zip(jax.tree.leaves(restored), jax.tree.leaves(state))
)
print(json.dumps({"save": saved, "same": same}))
"""


def test_a_replicated_state_is_saved_without_compiling_and_restores(tmp_path):
    """A state replicated over two devices is saved without compiling (orbax's
    replica-parallel save slices every array with a jax op, a program per shape and
    device: 14 here) and restores to the same values."""
    result = run_python(COMPILES_SCRIPT, str(tmp_path), device_count=2)
    counts = json.loads(result.stdout.strip().splitlines()[-1])
    assert counts == {"save": 0, "same": True}
    assert "overriding" not in result.stderr


def _no_space(kind: str) -> Exception:
    """A full disk as Python's own writes report it, or as tensorstore reports it to orbax."""
    if kind == "tensorstore":
        return ValueError(
            'RESOURCE_EXHAUSTED: Error writing "params.w/0" in OCDBT database: Failed to write '
            "295463 bytes to file 5: No space left on device [os_error_code='28']"
        )
    return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), "process_0-of-1.json")


@pytest.mark.parametrize("kind", ["oserror", "tensorstore", "checksums"])
def test_a_save_that_finds_the_disk_full_says_so_in_one_line_and_keeps_the_last_checkpoint(
    tmp_path, monkeypatch, caplog, kind
):
    import grain
    import jax.numpy as jnp

    from gld.files import DiskFullError
    from gld.runs.state import TrainState

    def state_at(step: int) -> TrainState:
        return TrainState(
            step=jnp.int32(step),
            params={"w": step * jnp.arange(4.0)},
            batch_stats={},
            opt_state=(),
            rng=jnp.zeros(2, jnp.uint32),
        )

    iterator = iter(grain.MapDataset.range(10).to_iter_dataset())
    manager = checkpoint_lib.checkpoint_manager(tmp_path)
    checkpoint_lib.save_checkpoint(manager, state_at(2), iterator)

    def full_disk(*args, **kwargs):
        raise _no_space(kind)

    if kind == "checksums":  # orbax has written the step; its checksums.json finds no room
        monkeypatch.setattr(checkpoint_lib, "write_atomically", full_disk)
    else:  # grain's iterator handler runs in orbax's background save thread
        monkeypatch.setattr(grain.checkpoint.CheckpointHandler, "save", full_disk)
    with pytest.raises(DiskFullError) as stopped:
        checkpoint_lib.save_checkpoint(manager, state_at(4), iterator)
    message = str(stopped.value)
    assert "\n" not in message
    assert message.startswith(f"disk full: no space left in {tmp_path / 'checkpoints'} ")
    assert "step 4" in message and "(newest: step 2)" in message
    # Orbax's own logs of the failure (one traceback per thread) are held back.
    assert not [record for record in caplog.records if record.levelno >= logging.ERROR]
    manager.close()
    # What the failed save wrote is gone; the checkpoint before it restores.
    assert sorted(path.name for path in (tmp_path / "checkpoints").iterdir()) == ["2"]
    manager = checkpoint_lib.checkpoint_manager(tmp_path)
    restored = checkpoint_lib.restore_intact_checkpoint(manager, state_at(0), print_fn=pytest.fail)
    manager.close()
    assert restored.step == 2 and restored.state.params["w"].tolist() == [0.0, 2.0, 4.0, 6.0]


def test_an_error_that_ends_a_run_is_not_replaced_by_what_closing_the_manager_says(
    tmp_path, monkeypatch
):
    import orbax.checkpoint as ocp

    from gld.files import DiskFullError

    def close_fails(self):
        # What orbax raises when a failed save's partial files were removed under it.
        raise FileNotFoundError(errno.ENOENT, "No such file or directory", "_CHECKPOINT_METADATA")

    monkeypatch.setattr(ocp.CheckpointManager, "close", close_fails)
    with pytest.raises(DiskFullError, match="^disk full: no room$"):
        with checkpoint_lib.saving_manager(tmp_path, keep=1):
            raise DiskFullError("disk full: no room")
    # Without an error to keep, a failing close is not hidden.
    with pytest.raises(FileNotFoundError, match="_CHECKPOINT_METADATA"):
        with checkpoint_lib.saving_manager(tmp_path, keep=1):
            pass
