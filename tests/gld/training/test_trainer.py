import dataclasses
import json
import os
import shutil
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest
from conftest import REPO_ROOT, TINY_MODEL, run_on_cpu_devices, tiny_train_config

from gld import input_pipeline
from gld.losses import supervised as losses
from gld.models import registry
from gld.runs import checkpoints as checkpoint_lib
from gld.runs import state as state_lib
from gld.runs import workdir as workdir_lib
from gld.runs.optimizer import make_optimizer
from gld.training import loop
from gld.training import trainer as train


def _params_of(workdir):
    _, variables, _ = workdir_lib.load_trained(workdir)
    return variables["params"]


# The loss weight is cast to float32 on purpose: it overflows to inf.
@pytest.mark.slow
@pytest.mark.filterwarnings("ignore:overflow encountered in cast:RuntimeWarning")
def test_nan_loss_stops_the_run_naming_the_step_and_keeps_the_last_good_checkpoint(
    tiny_scenes, tmp_path
):
    source = tiny_scenes.as_data_source("train")
    train.train_and_evaluate(
        tiny_train_config(), tmp_path, source, progress=False, print_fn=lambda _: None
    )
    good = _params_of(tmp_path)
    stored = (tmp_path / "config.json").read_bytes()
    messages = []
    with pytest.raises(loop.NonFiniteLossError, match="at step 5"):
        train.train_and_evaluate(
            # Finite, but infinite in float32: the loss overflows on the first step.
            tiny_train_config(steps=8, depth_weight=1e39),
            tmp_path,
            source,
            progress=False,
            print_fn=messages.append,
        )
    manager = checkpoint_lib.checkpoint_manager(tmp_path)
    assert manager.latest_step() == 4
    manager.close()
    jax.tree_util.tree_map(np.testing.assert_array_equal, _params_of(tmp_path), good)
    # The changed options are reported, but no step of them was kept: config.json stays.
    assert any("depth_weight 5.0 -> 1e+39, steps 4 -> 8" in m for m in messages)
    assert (tmp_path / "config.json").read_bytes() == stored


@pytest.fixture(scope="module")
def four_step_run(tiny_scenes, tmp_path_factory):
    """A tiny run of 4 steps, checkpoints at steps 2 and 4, metrics at every step."""
    run_dir = tmp_path_factory.mktemp("four_steps") / "run"
    config = tiny_train_config(log_every=1)
    train.train_and_evaluate(
        config, run_dir, tiny_scenes.as_data_source("train"), progress=False, print_fn=_quiet
    )
    return run_dir, config


def _quiet(_):
    pass


def _metrics_steps(run_dir):
    lines = (run_dir / "metrics.jsonl").read_text().splitlines()
    return [(record["step"], record["split"]) for record in map(json.loads, lines)]


def test_resume_skips_a_damaged_latest_checkpoint_and_trains_to_the_same_state(
    four_step_run, tiny_scenes, tmp_path
):
    original, config = four_step_run
    run_dir = tmp_path / "run"
    shutil.copytree(original, run_dir)
    step_dir = run_dir / "checkpoints" / "4"
    damaged = max(
        (path for path in (step_dir / "state").rglob("*") if path.is_file()),
        key=lambda path: path.stat().st_size,
    )
    data = bytearray(damaged.read_bytes())
    data[len(data) // 2] ^= 0x01
    damaged.write_bytes(bytes(data))

    messages = []
    state = train.train_and_evaluate(
        config,
        run_dir,
        tiny_scenes.as_data_source("train"),
        progress=False,
        print_fn=messages.append,
    )
    assert f"checkpoint step 4 skipped: {damaged} does not match its saved SHA-256" in messages
    assert f"resumed from step 2 in {run_dir / 'checkpoints'}" in messages
    [moved] = (run_dir / "corrupt_checkpoints").iterdir()
    assert moved.name.startswith("4-") and (moved / damaged.relative_to(step_dir)).exists()
    # Steps 3 and 4 trained again, with the same data, to the same parameters.
    assert int(state.step) == 4
    _, expected, _ = workdir_lib.load_trained(original)
    jax.tree_util.tree_map(
        np.testing.assert_array_equal, jax.device_get(state.params), expected["params"]
    )
    jax.tree_util.tree_map(np.testing.assert_array_equal, _params_of(run_dir), expected["params"])
    # One metrics line per step: the lines of steps 3 and 4 were dropped, then rewritten.
    assert _metrics_steps(run_dir) == [(step, "train") for step in (1, 2, 3, 4)]
    assert "metrics.jsonl: dropped 2 lines after step 2" in messages


KEEP_COMPILED_SCRIPT = textwrap.dedent(
    """
    import hashlib, json, logging, sys
    import jax, numpy as np
    import data
    from gld.training import trainer as train
    hits = []
    class Hits(logging.Handler):
        def emit(self, record):
            if "Persistent compilation cache hit" in record.getMessage():
                hits.append(record.getMessage().split("'")[1])
    compiler = logging.getLogger("jax._src.compiler")
    compiler.setLevel(logging.DEBUG)
    compiler.addHandler(Hits())
    sys.path.insert(0, "tests")
    from conftest import tiny_train_config
    builder = data.get_builder("gld_scenes/tiny", sys.argv[1])
    state = train.train_and_evaluate(tiny_train_config(steps=2), sys.argv[2],
                                     builder.as_data_source("train"), progress=False,
                                     print_fn=lambda _: None, keep_compiled=True)
    leaves = jax.tree_util.tree_leaves(jax.device_get(state.params))
    digest = hashlib.sha256(b"".join(np.asarray(l).tobytes() for l in leaves)).hexdigest()
    print(json.dumps({"hits": sorted(set(hits)), "params": digest}))
    """
)


# Two trainings in fresh interpreters: with the slow tests.
@pytest.mark.slow
def test_a_launch_keeps_its_compiled_programs_and_the_next_one_loads_them(
    tiny_scenes_dir, tmp_path
):
    workdir = tmp_path / "run"
    trained = run_on_cpu_devices(KEEP_COMPILED_SCRIPT, 1, str(tiny_scenes_dir), str(workdir))
    kept = sorted(path.name for path in (workdir / workdir_lib.COMPILE_CACHE_DIR).iterdir())
    assert trained["hits"] == []
    assert any(name.startswith("jit_train_step-") for name in kept), kept
    # The run trained again from scratch in its workdir (JAX's cache key holds the cache's
    # path) loads those programs rather than compiling them, to the same parameters.
    for path in workdir.iterdir():
        if path.name != workdir_lib.COMPILE_CACHE_DIR:
            shutil.rmtree(path) if path.is_dir() else path.unlink()
    again = run_on_cpu_devices(KEEP_COMPILED_SCRIPT, 1, str(tiny_scenes_dir), str(workdir))
    assert {"jit_init", "jit_train_step"} <= set(again["hits"]), again["hits"]
    assert again["params"] == trained["params"]


def test_changed_options_are_stored_only_by_a_launch_that_trains(
    four_step_run, tiny_scenes, tmp_path
):
    original, config = four_step_run
    run_dir = tmp_path / "run"
    shutil.copytree(original, run_dir)
    source = tiny_scenes.as_data_source("train")
    stored = (run_dir / "config.json").read_bytes()

    # The run is finished: a relaunch with another learning rate trains nothing, so
    # it stores nothing, not even its flags.
    messages = []
    changed = dataclasses.replace(config, learning_rate=1e-3)
    records = {"flags.txt": "--learning_rate=0.001\n"}
    train.train_and_evaluate(
        changed, run_dir, source, progress=False, print_fn=messages.append, records=records
    )
    assert any(
        "learning_rate 0.0001 -> 0.001 (not stored: no step to train beyond 4)" in m
        for m in messages
    )
    assert (run_dir / "config.json").read_bytes() == stored
    assert not (run_dir / "flags.txt").exists()

    # Two more steps with it: stored with the first checkpoint, and kept in the history.
    longer = dataclasses.replace(changed, steps=6)
    records = {"flags.txt": "--learning_rate=0.001\n--steps=6\n"}
    train.train_and_evaluate(longer, run_dir, source, progress=False, records=records)
    stored_config = workdir_lib.load_run_config(run_dir)
    assert (stored_config.learning_rate, stored_config.steps) == (1e-3, 6)
    [entry] = json.loads((run_dir / "config.json").read_text())["history"]
    assert entry["step"] == 4
    assert entry["changed"] == {
        "learning_rate": {"from": 1e-4, "to": 1e-3},
        "steps": {"from": 4, "to": 6},
    }
    assert (run_dir / "flags.txt").read_text() == records["flags.txt"]
    assert _metrics_steps(run_dir) == [(step, "train") for step in range(1, 7)]


@pytest.mark.slow  # learning is also checked by the true-flow test, in the default run
def test_the_model_overfits_eight_pairs_with_dense_supervision(tiny_scenes):
    source = tiny_scenes.as_data_source("train")
    batch = next(
        input_pipeline.eval_batches([source[i] for i in range(8)], batch_size=8, flow_source="gt")
    )
    batch = {key: batch[key] for key in ("image1", "image2", "flow", "depth")}
    batch["sparse_mask"] = batch["depth"] > 0  # dense supervision
    model = registry.make_model("global_local", **TINY_MODEL)
    optimizer = make_optimizer(3e-3)
    state = state_lib.create_train_state(model, optimizer, 48, 64, seed=0)
    step = jax.jit(
        train.make_train_step(
            model=model, optimizer=optimizer, loss_weights=losses.LossWeights(smoothness=0.0)
        )
    )
    history = []
    for _ in range(600):
        state, step_metrics = step(state, batch, jax.random.key(0))
        history.append(float(step_metrics["loss"]))
    assert np.isfinite(history).all()
    assert history[0] / min(history[-20:]) >= 10.0


SHARDED_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax, numpy as np
    from gld import sharding
    from gld.losses import supervised as losses
    from gld.training import loop
    from gld.training import trainer as train
    from gld.models import registry
    from gld.runs import state as state_lib
    from gld.runs.optimizer import make_optimizer

    assert len(jax.devices()) == 4
    # The paper's model, or (argument "recipe") the main job's: the pose searched and
    # refined on the flow, the flow derotated and triangulated under it; or (argument
    # "eigen") Eigen, whose dense layer of 1M parameters is split over the devices.
    recipe = len(sys.argv) > 1 and sys.argv[1] == "recipe"
    split = len(sys.argv) > 1 and sys.argv[1] == "eigen"
    options = dict(pose_refinement_steps=3, pose_refinement_starts=5, derotate_flow=True,
                   parallax_depth=True) if recipe else {}
    model = (registry.make_model("eigen") if split else
             registry.make_model("global_local", encoder_channels=[4, 8, 8, 8, 8], **options))
    optimizer = make_optimizer(1e-3)
    rng = np.random.default_rng(0)
    batch = {
        "image1": rng.uniform(-0.5, 0.5, (8, 24, 32, 3)).astype(np.float32),
        "image2": rng.uniform(-0.5, 0.5, (8, 24, 32, 3)).astype(np.float32),
        "flow": rng.normal(size=(8, 24, 32, 2)).astype(np.float32),
        "depth": rng.uniform(1, 5, (8, 24, 32)).astype(np.float32),
        "sparse_mask": rng.uniform(size=(8, 24, 32)) < 0.05,
        "intrinsics1": np.tile(np.float32([0.9, 1.2, 0.5, 0.5]), (8, 1)),
        "intrinsics2": np.tile(np.float32([0.9, 1.2, 0.5, 0.5]), (8, 1)),
    }
    keys = train.batch_keys(model, losses.LossWeights())
    results = {}
    for name, devices in (("one", jax.devices()[:1]), ("four", jax.devices())):
        mesh = sharding.make_mesh(devices)
        state = state_lib.create_train_state(model, optimizer, 24, 32, seed=0)
        placement = sharding.state_sharding(state, mesh)
        state = jax.device_put(state, placement)
        step = loop.jit_train_step(
            train.make_train_step(model=model, optimizer=optimizer,
                                  loss_weights=losses.LossWeights()), mesh, placement)
        for _ in range(2):
            global_batch = sharding.to_global_batch(batch, mesh, keys)
            state, _ = step(state, global_batch, jax.random.key(1))
        leaves = jax.tree_util.tree_leaves(jax.device_get(state.params))
        results[name] = np.concatenate([np.ravel(leaf) for leaf in leaves])
        if name == "four":
            assert len(global_batch["image1"].sharding.device_set) == 4
            # The state stays where it was placed: split only where asked.
            kept_split = [not leaf.sharding.is_fully_replicated
                          for leaf in jax.tree_util.tree_leaves(state)]
            assert any(kept_split) == split, kept_split
            if split:
                # Split parameters are gathered where a layer is computed whole: the
                # program's all-gathers are not the batch's.
                continue
            # Each device runs the per-example filter banks on its own two examples:
            # nothing gathers the batch onto every device.
            with jax.set_mesh(mesh):
                compiled = step.__wrapped__.lower(
                    state, global_batch, jax.random.key(1)).compile().as_text()
            assert "all-gather(" not in compiled, "the batch is gathered on every device"
            # Each pair's pose is searched and refined on its own device: no step of it
            # is resharded between devices.
            assert "all-to-all(" not in compiled, "examples move between devices"
    print(json.dumps({
        "max_abs_diff": float(np.max(np.abs(results["one"] - results["four"]))),
        "max_abs": float(np.max(np.abs(results["one"]))),
    }))
    """
)


# The main job's model compiles for ~40 s on two cores, Eigen's step ~30 s: with the slow
# tests.
@pytest.mark.parametrize(
    "model",
    [
        "paper",
        pytest.param("eigen", marks=pytest.mark.slow),
        pytest.param("recipe", marks=pytest.mark.slow),
    ],
)
def test_four_device_step_equals_one_device_step(tmp_path, model):
    numbers = run_on_cpu_devices(SHARDED_SCRIPT, 4, model)
    assert numbers["max_abs_diff"] <= 1e-5 * max(numbers["max_abs"], 1.0)


SPLIT_RESUME_SCRIPT = textwrap.dedent(
    """
    import json, shutil, sys
    from pathlib import Path
    import jax, numpy as np
    import data
    from gld.runs import config as config_lib
    from gld.runs import workdir as workdir_lib
    from gld.training import trainer as train
    assert len(jax.devices()) == 2
    source = data.get_builder("gld_scenes/tiny", sys.argv[1]).as_data_source("train")
    root = Path(sys.argv[2])
    config = config_lib.TrainConfig(model="eigen", batch_size=4, steps=4, log_every=2,
                                    eval_every=0, checkpoint_every=2,
                                    dataset="gld_scenes/tiny", height=48, width=64)
    quiet = lambda _: None
    whole = train.train_and_evaluate(config, root / "whole", source, progress=False,
                                     print_fn=quiet)
    split = [not leaf.sharding.is_fully_replicated for leaf in jax.tree_util.tree_leaves(whole)]
    shutil.copytree(root / "whole", root / "resumed")
    shutil.rmtree(root / "resumed" / "checkpoints" / "4")
    messages = []
    resumed = train.train_and_evaluate(config, root / "resumed", source, progress=False,
                                       print_fn=messages.append)
    _, stored, _ = workdir_lib.load_trained(root / "resumed")
    equal = lambda a, b: jax.tree_util.tree_all(jax.tree_util.tree_map(
        lambda x, y: bool(np.array_equal(x, y)), a, b))
    params = jax.device_get(whole.params)
    print(json.dumps({
        "split": sum(split),
        "resumed": f"resumed from step 2 in {root / 'resumed' / 'checkpoints'}" in messages,
        "same": equal(params, jax.device_get(resumed.params)),
        "same_stored": equal(params, stored["params"]),
    }))
    """
)


# Two devices, two trainings of Eigen: with the slow tests.
@pytest.mark.slow
def test_a_run_with_a_split_state_resumes_to_the_same_parameters(tiny_scenes_dir, tmp_path):
    # Eigen's first dense layer (4M parameters at 64x48) and its Adam moments are split over
    # the two devices; the checkpoint of step 2 holds them whole, and steps 3 and 4 train again
    # to the same bits.
    numbers = run_on_cpu_devices(SPLIT_RESUME_SCRIPT, 2, str(tiny_scenes_dir), str(tmp_path))
    assert numbers == {"split": 3, "resumed": True, "same": True, "same_stored": True}


TWO_PROCESS_SCRIPT = textwrap.dedent(
    """
    import hashlib, sys
    import jax, numpy as np
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=sys.argv[1], num_processes=2,
                               process_id=int(sys.argv[2]))
    import data
    from gld.runs import config as config_lib
    from gld.training import trainer as train
    builder = data.get_builder("gld_scenes/tiny", sys.argv[3])
    config = config_lib.TrainConfig(model_config={"encoder_channels": [4, 8, 8, 8, 8]},
                               batch_size=4, steps=3, log_every=1, eval_every=0,
                               checkpoint_every=3, dataset="gld_scenes/tiny", height=48,
                               width=64)
    state = train.train_and_evaluate(config, sys.argv[4], builder.as_data_source("train"),
                                     progress=False, print_fn=lambda _: None)
    leaves = jax.tree_util.tree_leaves(jax.device_get(state.params))
    digest = hashlib.sha256(b"".join(np.asarray(l).tobytes() for l in leaves)).hexdigest()
    print("PARAMS", jax.process_index(), jax.process_count(), len(jax.devices()), digest)
    """
)


# Two processes over gloo: slow; the four-device test covers the sharded step itself.
@pytest.mark.slow
def test_two_processes_train_with_identical_parameters(tiny_scenes_dir, tmp_path):
    import portpicker

    address = f"127.0.0.1:{portpicker.pick_unused_port()}"
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
    workers = [
        subprocess.Popen(
            [
                sys.executable,
                "-c",
                TWO_PROCESS_SCRIPT,
                address,
                str(index),
                str(tiny_scenes_dir),
                str(tmp_path / "run"),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=env,
        )
        for index in range(2)
    ]
    outputs = [worker.communicate(timeout=300) for worker in workers]
    for worker, (_, stderr) in zip(workers, outputs, strict=True):
        assert worker.returncode == 0, stderr[-3000:]
    lines = [
        next(line for line in out.splitlines() if line.startswith("PARAMS")).split()
        for out, _ in outputs
    ]
    assert [line[1] for line in lines] == ["0", "1"]
    assert all(line[2] == "2" and line[3] == "2" for line in lines)  # 2 processes, 2 devices
    assert lines[0][4] == lines[1][4]
    # only process 0 writes the logs
    log = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    records = [json.loads(line) for line in log]
    assert [r["step"] for r in records] == [1, 2, 3]


@pytest.fixture(scope="module")
def sixteen_pairs_dense(tiny_scenes):
    """The first 16 training pairs as one batch: true flow, every valid pixel supervised."""
    source = tiny_scenes.as_data_source("train")
    batch = next(
        input_pipeline.eval_batches([source[i] for i in range(16)], batch_size=16, flow_source="gt")
    )
    batch["sparse_mask"] = batch["depth_valid"]
    return batch


@pytest.mark.slow
def test_a_few_hundred_steps_learn_each_pairs_depth_map_with_true_flow(sixteen_pairs_dense):
    """With flow on the scale of the other inputs (the model's default flow_scale), 300
    Adam steps on 16 pairs with true flow and dense labels learn every pair's scale and
    most of its structure; with the flow at 1/10 of that scale (flow_scale=1, the
    original input) the same budget leaves the structure at a correlation of ~0.88."""
    from gld.analysis import probes

    batch = sixteen_pairs_dense
    model = registry.make_model("global_local", **TINY_MODEL)
    optimizer = make_optimizer(1e-3)
    state = state_lib.create_train_state(model, optimizer, 48, 64, seed=0)
    step = jax.jit(
        train.make_train_step(model=model, optimizer=optimizer, loss_weights=losses.LossWeights())
    )
    keys = ("image1", "image2", "flow", "depth", "sparse_mask")
    for _ in range(300):
        state, _ = step(state, {k: batch[k] for k in keys}, jax.random.key(0))
    outputs = model.apply(state.variables(), batch["image1"], batch["image2"], batch["flow"])
    valid = batch["depth_valid"]
    inv_true = np.asarray(losses.inverse_depth_target(batch["depth"], valid))
    pairs = probes.pair_statistics(np.asarray(outputs["inv_depth"]), inv_true, valid)
    statistics = probes.depth_statistics(pairs)
    assert statistics["pair_scale_correlation"] > 0.95
    assert statistics["within_pair_correlation"] > 0.93


# Compiling the self-supervised step (U-Net, pose net, warps at four scales) takes ~20 s.
@pytest.mark.slow
def test_a_self_supervised_model_trains_on_images_and_cameras_alone(tiny_scenes, tmp_path):
    from gld.evaluation import evaluate as evaluation

    config = tiny_train_config(
        model="struct2depth", model_config={}, learning_rate=1e-4, steps=2, log_every=1
    )
    assert config.validate().loss_weights().smoothness == config.photometric_smoothness_weight
    source = tiny_scenes.as_data_source("train")
    train.train_and_evaluate(config, tmp_path, source, progress=False, print_fn=lambda _: None)
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [record["step"] for record in records] == [1, 2]
    for record in records:
        assert {"photometric", "auto_mask_fraction"} <= set(record)
        assert "depth_l1" not in record  # no depth label is read
        assert np.isfinite(record["loss"]) and record["grad_norm"] > 0
    model, variables, _ = workdir_lib.load_trained(tmp_path)
    per_example, _ = evaluation.evaluate_source(
        model, variables, tiny_scenes.as_data_source("test"), batch_size=4, max_examples=4
    )
    assert np.all(np.isfinite(per_example["abs_inv"][per_example["example_mask"]]))


def test_a_model_given_the_true_pose_trains_and_evaluates_on_the_batches_pose(
    tiny_scenes, tmp_path
):
    """The pose reaches the model in training (augmented with the images) and in
    evaluation; a predictor asks for odometry, and the exported model takes it after
    the flow."""
    from gld.evaluation import evaluate as evaluation
    from gld.inference import export, predict
    from gld.inference.deploy import DeployedModel

    config = tiny_train_config(
        model_config={**TINY_MODEL, "global_source": "pose"}, eval_every=4, log_every=1
    )
    train.train_and_evaluate(
        config,
        tmp_path,
        tiny_scenes.as_data_source("train"),
        tiny_scenes.as_data_source("test"),
        progress=False,
        print_fn=lambda _: None,
    )
    model, variables, _ = workdir_lib.load_trained(tmp_path)
    assert model.extra_inputs == ("rotation", "translation")
    assert "global_encoder" not in variables["params"]
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert all(np.isfinite(r["loss"]) for r in records if r["split"] == "train")
    assert [r["abs_inv"] > 0 for r in records if r["split"] == "test"] == [True]
    # The same pairs scored with the wrong pose score differently: the pose is read.
    test_source = tiny_scenes.as_data_source("test")
    per_pair, _ = evaluation.evaluate_source(model, variables, test_source, batch_size=4)
    flipped = [dict(test_source[i], translation=-test_source[i]["translation"]) for i in range(4)]
    per_pair_flipped, _ = evaluation.evaluate_source(model, variables, flipped, batch_size=4)
    assert not np.allclose(per_pair["abs_inv"][:4], per_pair_flipped["abs_inv"])
    # A predictor takes the pose from odometry, and refuses to predict without it.
    predictor = predict.DepthPredictor(model, variables, 48, 64)
    assert predictor.given_pose == "pose"
    image = np.zeros((48, 64, 3), np.uint8)
    with pytest.raises(ValueError, match="give the pair's odometry"):
        predictor(image, image)
    export.export_model(model, variables, tmp_path / "model.gldx", height=48, width=64)
    deployed = DeployedModel.load(tmp_path / "model.gldx")
    assert deployed.extra_inputs == ("rotation", "translation")
    rng = np.random.default_rng(0)
    images = rng.integers(0, 256, (2, 48, 64, 3), dtype=np.uint8)
    flow = rng.normal(0, 2, (48, 64, 2)).astype(np.float32)
    inputs = (images[0], images[1], flow)
    pose = {"rotation": np.eye(3, dtype=np.float32), "translation": np.float32([0.6, 0, 0.8])}
    expected = model.apply(
        variables,
        *[image[None] / np.float32(255) - np.float32(0.5) for image in images],
        flow[None],
        **{key: value[None] for key, value in pose.items()},
    )
    np.testing.assert_allclose(deployed(*inputs, **pose), expected["depth"][0], rtol=1e-4)
    with pytest.raises(ValueError, match=r"also reads \['rotation', 'translation'\]"):
        deployed(*inputs)


# 300 steps at batch 16 (~45 s); the term's value is checked in tests/gld/losses.
@pytest.mark.slow
def test_the_epipolar_term_teaches_the_global_parameters_the_motion(sixteen_pairs_dense):
    """150 steps on 16 pairs with true flow: with the epipolar term the pose g stands for
    approaches the true motion (translation direction ~32 deg off, from ~66), with the
    depth loss alone it does not (~58 deg)."""
    from gld import geometry

    batch = sixteen_pairs_dense
    model = registry.make_model("global_local", **TINY_MODEL)
    optimizer = make_optimizer(1e-3)

    def direction_error(epipolar):
        weights = losses.LossWeights(smoothness=0.0, epipolar=epipolar)
        state = state_lib.create_train_state(model, optimizer, 48, 64, seed=0)
        step = jax.jit(
            train.make_train_step(model=model, optimizer=optimizer, loss_weights=weights)
        )
        keys = train.batch_keys(model, weights)
        assert ("intrinsics1" in keys) == (epipolar > 0)
        for _ in range(150):
            state, _ = step(state, {k: batch[k] for k in keys}, jax.random.key(0))
        outputs = model.apply(state.variables(), batch["image1"], batch["image2"], batch["flow"])
        error = geometry.translation_error_degrees(
            np.asarray(outputs["global_pose"]["translation"]), batch["translation"]
        )
        return float(np.mean(np.minimum(error, 180.0 - error)))  # the sign is not observable

    with_term, without = direction_error(1.0), direction_error(0.0)
    assert with_term < 40.0 < 50.0 < without
