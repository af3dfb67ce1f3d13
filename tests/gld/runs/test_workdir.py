"""A run's workdir: the stored configuration and its history, the architecture guard, old
workdirs, the lock, verified checkpoints, the metrics log."""

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from conftest import REPO_ROOT, TINY_MODEL, tiny_train_config

from gld import files as files_lib
from gld import input_pipeline
from gld.models import registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import lock as lock_lib
from gld.runs import metrics_log, workdir
from gld.runs import state as state_lib
from gld.training import trainer as train


def _quiet(_):
    pass


def test_a_workdir_refuses_another_architecture_listing_the_flags_and_writes_nothing(
    tiny_scenes, tmp_path
):
    source = tiny_scenes.as_data_source("train")
    workdir.write_run_config(tmp_path, tiny_train_config(steps=2))
    stored = (tmp_path / "config.json").read_bytes()
    other = tiny_train_config(model_config=dict(TINY_MODEL, global_dim=3, use_coordinates=False))
    with pytest.raises(ValueError, match="global_dim.*use_coordinates"):
        train.train_and_evaluate(
            other, tmp_path, source, progress=False, print_fn=_quiet, records={"flags.txt": "x"}
        )
    assert (tmp_path / "config.json").read_bytes() == stored
    assert sorted(path.name for path in tmp_path.iterdir()) == ["config.json"]
    # a speed-only choice is not architecture
    same = tiny_train_config(steps=2, model_config=dict(TINY_MODEL, filter_formulation="vmap"))
    assert workdir.check_run_config(tmp_path, same) == {
        "model_config.filter_formulation": (None, "vmap")
    }


def test_another_model_is_refused_naming_the_model_alone(tmp_path):
    from gld.arguments import ArgumentError

    workdir.write_run_config(tmp_path, tiny_train_config(steps=2))
    other = tiny_train_config(model="small_encdec", model_config={})
    with pytest.raises(ArgumentError) as refused:
        workdir.check_run_config(tmp_path, other)
    assert str(refused.value) == (
        f"--model=small_encdec: workdir {tmp_path} holds a run of model 'global_local'; "
        "use another --workdir, or --model=global_local"
    )
    # The same model: each differing option named as its flag, both values given.
    other = tiny_train_config(model_config=dict(TINY_MODEL, global_dim=3))
    with pytest.raises(ArgumentError) as refused:
        workdir.check_run_config(tmp_path, other)
    assert "(--global_dim=6 there, 3 now)" in str(refused.value)


def test_bad_options_and_record_names_fail_before_the_workdir_exists(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("train")
    run_dir = tmp_path / "run"
    with pytest.raises(ValueError, match="foo"):
        train.train_and_evaluate(
            tiny_train_config(model="foo"), run_dir, source, progress=False, print_fn=_quiet
        )
    for name in ("config.json", "../flags.txt"):
        with pytest.raises(ValueError, match="record name"):
            train.train_and_evaluate(
                tiny_train_config(), run_dir, source, progress=False, records={name: "x"}
            )
    assert not run_dir.exists()


def test_a_run_stores_every_architecture_value_and_old_runs_keep_theirs(tmp_path):
    config = tiny_train_config()
    workdir.write_run_config(tmp_path, config)
    stored = json.loads((tmp_path / "config.json").read_text())
    # Defaults are written out, so a later change of a default cannot change this run.
    assert stored["architecture"]["flow_scale"] == 10.0
    assert stored["config"]["model_config"]["global_norm"] == "none"
    assert workdir.load_run_config(tmp_path).model_config["flow_scale"] == 10.0

    # A workdir written before flow_scale existed was trained on unscaled flow.
    old = tmp_path / "old"
    old.mkdir()
    for section in ("architecture", "config"):
        values = stored[section] if section == "architecture" else stored[section]["model_config"]
        for key in ("flow_scale", "global_norm", "modulation_scale"):
            values.pop(key)
    (old / "config.json").write_text(json.dumps(stored))
    loaded = workdir.load_run_config(old)
    assert loaded.model_config["flow_scale"] == 1.0
    assert registry.make_model(loaded.model, **loaded.model_config).flow_scale == 1.0
    with pytest.raises(ValueError, match="--flow_scale=1.0 there, 10.0 now"):
        workdir.write_run_config(old, config)


def test_a_workdir_stored_with_the_old_flow_key_loads_as_flow_source(tmp_path):
    workdir.write_run_config(tmp_path, tiny_train_config(flow_source="gt"))
    stored = json.loads((tmp_path / "config.json").read_text())
    assert stored["config"]["flow_source"] == "gt"
    # Workdirs written before the rename stored the flow under "flow".
    stored["config"]["flow"] = stored["config"].pop("flow_source")
    (tmp_path / "config.json").write_text(json.dumps(stored))
    assert workdir.load_run_config(tmp_path).flow_source == "gt"
    # ... and the renamed key is no change of options
    assert workdir.check_run_config(tmp_path, tiny_train_config(flow_source="gt")) == {}


def test_changed_options_replace_the_stored_config_and_are_kept_in_its_history(tmp_path):
    workdir.write_run_config(tmp_path, tiny_train_config(), records={"flags.txt": "--steps=4\n"})
    assert "history" not in json.loads((tmp_path / "config.json").read_text())
    assert not workdir.records_differ(tmp_path, {"flags.txt": "--steps=4\n"})
    assert workdir.records_differ(tmp_path, {"flags.txt": "--steps=8\n"})

    changed = tiny_train_config(steps=8, learning_rate=1e-3)
    assert workdir.check_run_config(tmp_path, changed) == {
        "learning_rate": (1e-4, 1e-3),
        "steps": (4, 8),
    }
    workdir.write_run_config(tmp_path, changed, step=4, records={"flags.txt": "--steps=8\n"})
    stored = json.loads((tmp_path / "config.json").read_text())
    assert stored["config"]["learning_rate"] == 1e-3
    [entry] = stored["history"]
    assert entry["step"] == 4
    assert entry["changed"] == {
        "learning_rate": {"from": 1e-4, "to": 1e-3},
        "steps": {"from": 4, "to": 8},
    }
    assert (tmp_path / "flags.txt").read_text() == "--steps=8\n"
    assert workdir.load_run_config(tmp_path).learning_rate == 1e-3

    # Rewriting the same options adds no entry; another change adds one after it.
    workdir.write_run_config(tmp_path, changed, step=6)
    workdir.write_run_config(tmp_path, tiny_train_config(steps=10, learning_rate=1e-3), step=8)
    history = json.loads((tmp_path / "config.json").read_text())["history"]
    assert [(h["step"], list(h["changed"])) for h in history] == [
        (4, ["learning_rate", "steps"]),
        (8, ["steps"]),
    ]
    # no temporary file is left behind
    assert sorted(p.name for p in tmp_path.iterdir()) == ["config.json", "flags.txt"]


def test_drop_metrics_after_keeps_one_line_per_step_up_to_the_restored_one(tmp_path):
    lines = [
        {"step": 2, "split": "train", "loss": 1.0},
        {"step": 2, "split": "test", "abs_inv": 0.5},
        {"step": 4, "split": "train", "loss": 0.9},
        {"step": 6, "split": "train", "loss": 0.8},
    ]
    text = "".join(json.dumps(line) + "\n" for line in lines)
    (tmp_path / "metrics.jsonl").write_text(text + '{"step": 8, "spl')  # cut by a kill
    assert metrics_log.drop_metrics_after(tmp_path, 4) == 2
    kept = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert kept == lines[:3]
    before = (tmp_path / "metrics.jsonl").stat().st_mtime_ns
    assert metrics_log.drop_metrics_after(tmp_path, 4) == 0
    assert (tmp_path / "metrics.jsonl").stat().st_mtime_ns == before
    assert metrics_log.drop_metrics_after(tmp_path / "none", 0) == 0


LOCK_HOLDER = textwrap.dedent(
    """
    import sys, time
    from gld.runs import lock
    lock.WorkdirLock(sys.argv[1]).acquire()
    print("locked", flush=True)
    time.sleep(300)
    """
)


def test_a_second_process_is_refused_naming_the_holder_until_the_holder_is_killed(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
    holder = subprocess.Popen(
        [sys.executable, "-c", LOCK_HOLDER, str(tmp_path)],
        stdout=subprocess.PIPE,
        text=True,
        env=env,
        cwd=REPO_ROOT,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(lock_lib.WorkdirLockedError) as refusal:
            lock_lib.WorkdirLock(tmp_path).acquire()
        message = str(refusal.value)
        assert f"pid {holder.pid} on host {socket.gethostname()}" in message
        assert "time.sleep(300)" in message and str(tmp_path) in message
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()
    # The kernel released the killed holder's lock.
    with lock_lib.WorkdirLock(tmp_path):
        owner = json.loads((tmp_path / "train.lock").read_text())
        assert owner["pid"] == os.getpid()
    assert (tmp_path / "train.lock").read_text() == ""


def test_training_in_a_locked_workdir_is_refused_before_writing_or_building(
    tiny_scenes, tmp_path, monkeypatch
):
    def not_reached(*args, **kwargs):
        raise AssertionError("the state was initialised before the lock was taken")

    # Initialising the state (compiling the model's init) is the costly part of a start-up.
    monkeypatch.setattr(train, "create_train_state", not_reached)
    source = tiny_scenes.as_data_source("train")
    with lock_lib.WorkdirLock(tmp_path):
        with pytest.raises(lock_lib.WorkdirLockedError, match=f"pid {os.getpid()} "):
            train.train_and_evaluate(
                tiny_train_config(), tmp_path, source, progress=False, print_fn=_quiet
            )
    assert sorted(path.name for path in tmp_path.iterdir()) == ["train.lock"]


def test_a_first_launch_that_fails_after_taking_the_lock_leaves_no_workdir(
    tiny_scenes, tmp_path, monkeypatch
):
    def fails(*args, **kwargs):
        raise RuntimeError("the start-up failed")

    monkeypatch.setattr(train, "create_train_state", fails)
    run_dir = tmp_path / "run"
    with pytest.raises(RuntimeError, match="the start-up failed"):
        train.train_and_evaluate(
            tiny_train_config(), run_dir, tiny_scenes.as_data_source("train"), progress=False
        )
    assert not run_dir.exists()
    # A workdir that existed before keeps its (emptied) lock file; one written in keeps all.
    run_dir.mkdir()
    with lock_lib.WorkdirLock(run_dir):
        pass
    assert (run_dir / "train.lock").read_text() == ""
    other = tmp_path / "other"
    with lock_lib.WorkdirLock(other):
        (other / "config.json").write_text("{}")
    assert sorted(path.name for path in other.iterdir()) == ["config.json", "train.lock"]


def test_a_lock_whose_file_its_holder_removed_meanwhile_locks_the_file_at_the_path(
    tmp_path, monkeypatch
):
    workdir_path = tmp_path / "run"
    first = lock_lib.WorkdirLock(workdir_path)
    first.acquire()
    locking = lock_lib.fcntl.flock

    def first_leaves_then_lock(fd, operation):
        # The first holder, which created the workdir and wrote nothing, releases it
        # between the second's open and its flock: the file the second opened is gone.
        monkeypatch.setattr(lock_lib.fcntl, "flock", locking)
        first.release()
        assert not workdir_path.exists()
        return locking(fd, operation)

    second = lock_lib.WorkdirLock(workdir_path)
    monkeypatch.setattr(lock_lib.fcntl, "flock", first_leaves_then_lock)
    second.acquire()
    monkeypatch.undo()
    assert json.loads((workdir_path / "train.lock").read_text())["pid"] == os.getpid()
    with pytest.raises(lock_lib.WorkdirLockedError):  # the file at the path is the held one
        lock_lib.WorkdirLock(workdir_path).acquire()
    second.release()


@pytest.fixture(scope="module")
def two_checkpoints_once(tiny_scenes, tmp_path_factory):
    """A workdir with checkpoints at steps 2 and 4 (different parameters) and the
    parameters of each."""
    config = tiny_train_config()
    run_dir = tmp_path_factory.mktemp("two_checkpoints") / "run"
    workdir.write_run_config(run_dir, config)
    model = registry.make_model(config.model, **config.model_config)
    state = state_lib.create_train_state(
        model, config.optimizer(), config.height, config.width, config.seed
    )
    iterator = iter(
        input_pipeline.train_dataset(
            tiny_scenes.as_data_source("train"), batch_size=4, seed=0, gt_pixels=1
        )
    )
    manager = checkpoint_lib.checkpoint_manager(run_dir)
    params = {}
    for step in (2, 4):
        state = state.replace(
            step=np.int32(step), params=jax.tree_util.tree_map(lambda p: p + 1.0, state.params)
        )
        params[step] = state.params
        checkpoint_lib.save_checkpoint(manager, state, iterator)
    manager.close()
    return run_dir, params


@pytest.fixture
def two_checkpoints(two_checkpoints_once, tmp_path):
    """A copy of `two_checkpoints_once` for one test, which may damage it."""
    run_dir, params = two_checkpoints_once
    return shutil.copytree(run_dir, tmp_path / "run"), params


def _largest_array_file(step_dir):
    files = [path for path in (step_dir / "state").rglob("*") if path.is_file()]
    return max(files, key=lambda path: path.stat().st_size)


def _flip_one_bit(path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0x10
    path.write_bytes(bytes(data))


def _truncate(path):
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 3])


def _assert_params_equal(actual, expected):
    jax.tree_util.tree_map(np.testing.assert_array_equal, actual, expected)


def test_a_checkpoint_records_the_checksum_of_each_of_its_files(two_checkpoints):
    run_dir, _ = two_checkpoints
    step_dir = run_dir / "checkpoints" / "4"
    recorded = json.loads((step_dir / "checksums.json").read_text())["files"]
    on_disk = {
        path.relative_to(step_dir).as_posix()
        for path in step_dir.rglob("*")
        if path.is_file() and path.name != "checksums.json"
    }
    assert set(recorded) == on_disk and "data/process_0-of-1.json" in recorded
    assert checkpoint_lib.verify_checksums(step_dir) is True


@pytest.mark.parametrize("damage", [_flip_one_bit, _truncate])
def test_a_damaged_latest_checkpoint_loads_the_previous_one_naming_the_file(
    two_checkpoints, damage
):
    run_dir, params = two_checkpoints
    damaged = _largest_array_file(run_dir / "checkpoints" / "4")
    damage(damaged)
    with pytest.warns(checkpoint_lib.CheckpointWarning) as caught:
        trained = workdir.restore_trained(run_dir)
    messages = [str(warning.message) for warning in caught]
    assert messages[0].startswith(f"checkpoint step 4 skipped: {damaged} ")
    assert messages[1:] == ["restored checkpoint step 2, the newest intact one (skipped: [4])"]
    assert trained.step == 2
    _assert_params_equal(trained.variables["params"], params[2])
    # asked for by step, the damaged one is an error, not another step
    with pytest.warns(checkpoint_lib.CheckpointWarning, match=f"step 4 skipped: {damaged}"):
        with pytest.raises(checkpoint_lib.CorruptCheckpointError, match=f"step 4 .*{damaged}"):
            workdir.load_trained(run_dir, step=4)
    assert damaged.exists()


def test_no_intact_checkpoint_is_a_clear_error_and_nothing_is_deleted(two_checkpoints):
    run_dir, _ = two_checkpoints
    for step in (2, 4):
        _flip_one_bit(_largest_array_file(run_dir / "checkpoints" / str(step)))
    files_before = sorted(run_dir.rglob("*"))
    with pytest.warns(checkpoint_lib.CheckpointWarning):
        with pytest.raises(
            checkpoint_lib.CorruptCheckpointError, match="no checkpoint in .* is intact"
        ):
            workdir.load_trained(run_dir)
    assert sorted(run_dir.rglob("*")) == files_before


def test_checkpoints_without_checksums_load_with_a_warning(two_checkpoints):
    run_dir, params = two_checkpoints
    for step in (2, 4):
        (run_dir / "checkpoints" / str(step) / "checksums.json").unlink()
    with pytest.warns(checkpoint_lib.CheckpointWarning, match="step 4 has no checksums.json"):
        trained = workdir.restore_trained(run_dir)
    assert trained.step == 4
    _assert_params_equal(trained.variables["params"], params[4])

    # Without checksums a truncated file is caught by the restore itself.
    _truncate(_largest_array_file(run_dir / "checkpoints" / "4"))
    messages = []
    trained = workdir.restore_trained(run_dir, print_fn=messages.append)
    assert trained.step == 2
    assert any(m.startswith("checkpoint step 4 skipped: restoring") for m in messages)


def test_the_metrics_log_is_read_in_order_without_a_line_cut_short(tmp_path):
    assert metrics_log.read_metrics(tmp_path) == []
    lines = [json.dumps({"step": 1, "split": "train"}), json.dumps({"step": 2, "split": "test"})]
    (tmp_path / "metrics.jsonl").write_text("\n".join(lines) + '\n{"step": 3, "spl')
    assert metrics_log.read_metrics(tmp_path) == [
        {"step": 1, "split": "train"},
        {"step": 2, "split": "test"},
    ]


def test_bytes_are_written_atomically_as_they_are(tmp_path):
    payload = bytes(range(256))
    files_lib.write_atomically(tmp_path / "blob.npz", payload)
    assert (tmp_path / "blob.npz").read_bytes() == payload
    assert [p.name for p in tmp_path.iterdir()] == ["blob.npz"]
