"""The skeleton every trainer runs, driven by a toy run: what a trainer adds is called in
order, nothing is written before everything is checked, a second launch is refused before
its start-up, a full disk ends the run in one line, and a relaunch resumes."""

import errno
import json
import os
from pathlib import Path

import flax.linen as nn
import jax
import jax.numpy as jnp
import optax
import pytest

from gld import input_pipeline
from gld.files import DiskFullError
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import lock as lock_lib
from gld.runs import metrics_log
from gld.runs.state import TrainState
from gld.runs.trainer_options import TrainerOptions
from gld.training import loop


class MeanDepth(nn.Module):
    """Predicts each pair's mean depth from its first image's mean colour."""

    @nn.compact
    def __call__(self, image1):
        return nn.Dense(1)(image1.mean(axis=(1, 2)))[:, 0]


class ToyRun(loop.TrainingRun):
    def __init__(self, config, refuse: bool = False):
        super().__init__(config)
        self.refuse = refuse
        self.calls: list[str] = []

    def make_model(self):
        self.calls.append("make_model")
        return MeanDepth()

    def check_workdir(self, workdir: Path):
        self.calls.append("check_workdir")
        if self.refuse:
            raise ValueError("the workdir holds another run")
        return None if not (workdir / "toy.json").exists() else {}

    def fresh_state(self, model, optimizer, workdir, print_fn):
        self.calls.append("fresh_state")
        params = model.init(jax.random.key(self.config.seed), jnp.zeros((1, 48, 64, 3)))["params"]
        return TrainState(
            step=jnp.zeros((), jnp.int32),
            params=params,
            batch_stats={},
            opt_state=optimizer.init(params),
            rng=jax.random.key_data(jax.random.key(1)),
        )

    def parameter_counts(self, state):
        return {"toy": 4}

    def batch_keys(self, model):
        return ("image1", "depth")

    def data_options(self):
        return {"gt_pixels": 0, "flow_source": "gt"}

    def train_step(self, model, optimizer):
        def step(state, batch, rng):
            def loss_fn(params):
                target = batch["depth"].mean(axis=(1, 2))
                return jnp.mean((model.apply({"params": params}, batch["image1"]) - target) ** 2)

            loss, grads = jax.value_and_grad(loss_fn)(state.params)
            updates, opt_state = optimizer.update(grads, state.opt_state, state.params)
            params = optax.apply_updates(state.params, updates)
            return state.replace(step=state.step + 1, params=params, opt_state=opt_state), {
                "loss": loss
            }

        return step

    def evaluation(self, model, mesh, test_source):
        def evaluate(state):
            self.calls.append("evaluate")
            return {"constant": 1.0}, "evaluated"

        return evaluate

    def begin(self, workdir, start_step, changes, print_fn):
        self.calls.append(f"begin at {start_step}, stored {changes is not None}")
        (workdir / "toy.json").write_text(json.dumps({"start": start_step}))
        return lambda: self.calls.append("after_checkpoint")


def _config(**values) -> TrainerOptions:
    values = {
        "batch_size": 4,
        "steps": 4,
        "log_every": 2,
        "eval_every": 4,
        "checkpoint_every": 2,
        "height": 48,
        "width": 64,
        "learning_rate": 1e-2,
        **values,
    }
    return TrainerOptions(**values)


def test_the_skeleton_runs_a_trainers_parts_in_order_and_resumes(tiny_scenes, tmp_path):
    source = tiny_scenes.as_data_source("train")
    run = ToyRun(_config())
    messages = []
    state = loop.train(run, tmp_path, source, source, progress=False, print_fn=messages.append)
    assert int(state.step) == 4
    assert run.calls == [
        "make_model",
        "check_workdir",  # before anything is written
        "check_workdir",  # again, under the lock, before the costly start-up
        "fresh_state",
        "begin at 0, stored False",
        "after_checkpoint",
        "after_checkpoint",
        "evaluate",
    ]
    assert "parameters toy: 4" in messages
    manager = checkpoint_lib.checkpoint_manager(tmp_path)
    assert manager.latest_step() == 4
    manager.close()
    logged = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [record["step"] for record in logged if "loss" in record] == [2, 4]
    # A relaunch with more steps resumes at the last checkpoint.
    again = ToyRun(_config(steps=6, eval_every=0))
    messages.clear()
    state = loop.train(again, tmp_path, source, progress=False, print_fn=messages.append)
    assert int(state.step) == 6
    assert any(message.startswith("resumed from step 4") for message in messages)
    assert "begin at 4, stored True" in again.calls


def test_a_refused_workdir_is_left_untouched(tiny_scenes, tmp_path):
    workdir = tmp_path / "run"
    run = ToyRun(_config(), refuse=True)
    with pytest.raises(ValueError, match="another run"):
        loop.train(run, workdir, tiny_scenes.as_data_source("train"), progress=False)
    assert not workdir.exists()
    assert run.calls == ["make_model", "check_workdir"]


def test_a_launch_on_a_held_workdir_is_refused_before_its_costly_start_up(
    tiny_scenes, tmp_path, monkeypatch
):
    def not_reached(*args, **kwargs):
        raise AssertionError("the data was opened before the lock was taken")

    monkeypatch.setattr(input_pipeline, "train_dataset", not_reached)
    run = ToyRun(_config())
    with lock_lib.WorkdirLock(tmp_path):
        with pytest.raises(lock_lib.WorkdirLockedError, match=f"pid {os.getpid()} "):
            loop.train(run, tmp_path, tiny_scenes.as_data_source("train"), progress=False)
    assert run.calls == ["make_model", "check_workdir"]  # no state was initialised
    assert sorted(path.name for path in tmp_path.iterdir()) == ["train.lock"]


def _full_disk_from_call(number: int, write):
    """`write` that reports a full disk from its `number`-th call on."""
    calls = []

    def write_or_fail(*args, **kwargs):
        calls.append(args)
        if len(calls) >= number:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return write(*args, **kwargs)

    return write_or_fail


@pytest.mark.parametrize("writing", ["checkpoint", "metrics"])
def test_a_full_disk_ends_the_run_in_one_line_and_the_relaunch_resumes(
    tiny_scenes, tmp_path, monkeypatch, writing
):
    import grain

    source = tiny_scenes.as_data_source("train")
    if writing == "checkpoint":
        # The second save (step 4) fails in grain's handler, inside orbax's save thread.
        handler = grain.checkpoint.CheckpointHandler
        monkeypatch.setattr(handler, "save", _full_disk_from_call(2, handler.save))
        where = f"no space left in {tmp_path / 'checkpoints'} to save the checkpoint of step 4"
    else:
        # The second metrics line (step 4) finds the disk full.
        logger = metrics_log.MetricsLogger
        monkeypatch.setattr(logger, "write", _full_disk_from_call(2, logger.write))
        where = f"no space left to write in {tmp_path};"
    run = ToyRun(_config(eval_every=0))
    with pytest.raises(DiskFullError) as stopped:
        loop.train(run, tmp_path, source, progress=False, print_fn=lambda _: None)
    message = str(stopped.value)
    assert message.startswith(f"disk full: {where}") and "\n" not in message
    assert "(newest: step 2)" in message
    monkeypatch.undo()
    # The lock was released and the step-2 checkpoint is intact: the relaunch resumes.
    messages = []
    state = loop.train(
        ToyRun(_config()), tmp_path, source, progress=False, print_fn=messages.append
    )
    assert f"resumed from step 2 in {tmp_path / 'checkpoints'}" in messages
    assert int(state.step) == 4
