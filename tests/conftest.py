"""Test-wide settings: CPU only, quiet TFDS, repo root importable."""

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

os.environ.setdefault("JAX_PLATFORMS", "cpu")
os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "3")

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

import pytest  # noqa: E402

# The files whose tests take longest start first: the parallel workers (one file each,
# `--dist=loadfile`) then end together rather than one waiting on a long file taken last.
LONGEST_FIRST = (
    "tests/experiments/test_paper_launcher.py",
    "tests/experiments/test_train_launcher.py",
    "tests/gld/training/test_trainer.py",
)


def pytest_collection_modifyitems(session, config, items):
    def rank(item):
        path = item.nodeid.split("::")[0]
        return LONGEST_FIRST.index(path) if path in LONGEST_FIRST else len(LONGEST_FIRST)

    items.sort(key=rank)  # stable: the order within and between the other files stays


def _interpreter(arguments, *, timeout: int, env=None, **options) -> subprocess.CompletedProcess:
    """A fresh Python interpreter with `arguments`, on the CPU, from the repository root;
    `env` adds variables to this environment, and removes those it gives as None."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT), **(env or {}))
    env = {name: value for name, value in env.items() if value is not None}
    return subprocess.run(
        [sys.executable, *arguments],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO_ROOT,
        timeout=timeout,
        **options,
    )


def run_isolated(script: str, *arguments) -> subprocess.CompletedProcess:
    """`script` in `python -I` (no PYTHONPATH, user site or working directory on sys.path:
    only site-packages), on the CPU, given `arguments` as one JSON argv entry."""
    return subprocess.run(
        [sys.executable, "-I", "-c", script, json.dumps(list(arguments))],
        capture_output=True,
        text=True,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
        timeout=300,
    )


def run_python(
    script: str, *args: str, device_count: int = 1, timeout: int = 300
) -> subprocess.CompletedProcess:
    """Runs `script` with `args` in a fresh interpreter on `device_count` CPU devices,
    from the repository root, and asserts that it exits cleanly."""
    result = _interpreter(
        ["-c", script, *args],
        timeout=timeout,
        env={"XLA_FLAGS": f"--xla_force_host_platform_device_count={device_count}"},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def launch(module: str, *args: str, timeout: int = 300, **options) -> subprocess.CompletedProcess:
    """Runs `python -m module args` on the CPU from the repository root and returns the
    finished process (its exit status is the caller's to check); `options` go to
    `subprocess.run`."""
    return _interpreter(["-m", module, *args], timeout=timeout, **options)


def run_on_cpu_devices(script: str, device_count: int, *args: str) -> dict:
    """`run_python` with `args` on `device_count` devices; the JSON object the script
    prints last."""
    result = run_python(script, *args, device_count=device_count)
    return json.loads(result.stdout.strip().splitlines()[-1])


# A small global encoder that keeps compile and step times of trainer tests low.
TINY_MODEL = {"encoder_channels": [4, 8, 8, 8, 8]}


def tiny_train_config(**overrides):
    """A TrainConfig for `gld_scenes/tiny` with TINY_MODEL: batch 4, 4 steps, a checkpoint
    every 2 steps, no periodic evaluation; `overrides` replace any field."""
    from gld.runs import config

    values = dict(
        model_config=dict(TINY_MODEL),
        batch_size=4,
        steps=4,
        log_every=2,
        eval_every=0,
        checkpoint_every=2,
        dataset="gld_scenes/tiny",
        height=48,
        width=64,
    )
    values.update(overrides)
    return config.TrainConfig(**values)


@pytest.fixture(scope="session")
def tiny_scenes_dir(tmp_path_factory):
    """A data_dir holding the built `gld_scenes/tiny` (64x48, 32 train / 16 test pairs)."""
    import data

    data_dir = tmp_path_factory.mktemp("tiny_scenes")
    data.prepare("gld_scenes/tiny", data_dir)
    return data_dir


@pytest.fixture(scope="session")
def tiny_scenes(tiny_scenes_dir):
    import data

    return data.get_builder("gld_scenes/tiny", tiny_scenes_dir)


@pytest.fixture(scope="session")
def trained_workdir(tiny_scenes, tmp_path_factory):
    """A tiny global-local run trained for 2 steps, with the train launcher's record of
    its dataset's flow."""
    from experiments import common
    from gld.inference import workdir_export
    from gld.training import trainer as train

    workdir = tmp_path_factory.mktemp("trained")
    config = tiny_train_config(steps=2, log_every=1)
    train.train_and_evaluate(
        config,
        workdir,
        tiny_scenes.as_data_source("train"),
        records={workdir_export.FLOW_RECORD: common.dataset_flow_record(tiny_scenes)},
        progress=False,
        print_fn=lambda _: None,
    )
    return workdir


@pytest.fixture(scope="session")
def eval_batch(tiny_scenes):
    """The first 4 test pairs as one evaluation batch."""
    from gld import input_pipeline

    source = tiny_scenes.as_data_source("test")
    return next(input_pipeline.eval_batches([source[i] for i in range(4)], batch_size=4))


def random_variables(model, height: int, width: int, seed: int, **inputs) -> dict:
    """Variables of `model`'s structure drawn with numpy (std 1/sqrt(fan-in), biases 0):
    jit-compiling `model.init` would cost seconds per test module. `inputs`: the model's
    extra inputs by keyword (a pose, the cameras) where it reads them."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    zeros = jax.ShapeDtypeStruct((1, height, width, 3), jnp.float32)
    flow = jax.ShapeDtypeStruct((1, height, width, 2), jnp.float32)
    shapes = jax.eval_shape(
        functools.partial(model.init, **inputs), jax.random.key(0), zeros, zeros, flow
    )
    rng = np.random.default_rng(seed)

    def draw(leaf):
        if len(leaf.shape) < 2:
            return np.zeros(leaf.shape, leaf.dtype)
        fan_in = int(np.prod(leaf.shape[:-1]))
        return rng.normal(0.0, fan_in**-0.5, leaf.shape).astype(leaf.dtype)

    return jax.tree_util.tree_map(draw, shapes)
