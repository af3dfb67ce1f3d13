"""Checkpoints of a run: which steps a workdir holds."""

from gld.runs import checkpoints as checkpoint_lib


def test_the_last_checkpointed_step_counts_only_written_steps(tmp_path):
    assert checkpoint_lib.last_checkpointed_step(tmp_path / "none") == 0
    checkpoints = tmp_path / "checkpoints"
    for name in ("2", "10", "12.orbax-checkpoint-tmp-1700000000", "notes"):
        (checkpoints / name).mkdir(parents=True)
    assert checkpoint_lib.last_checkpointed_step(tmp_path) == 10
