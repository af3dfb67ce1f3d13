"""The launchers run end to end in a subprocess on the tiny benchmark."""

import json
import os
import signal
import subprocess
import sys
import time

import h5py
import jax
import numpy as np
import pytest
from conftest import REPO_ROOT, launch

from gld import input_pipeline
from gld.evaluation import stored_predictions
from gld.models import registry
from gld.runs import recipe
from gld.runs import workdir as workdir_lib

# A few steps of a tiny model (the recipe's warm-up shrinks to fit: recipe.warmup_that_fits).
TINY_FLAGS = ["--encoder_channels=4,8,8,8,8", "--batch_size=4", "--log_every=2"]


def _launch(args, data_dir, dataset="gld_scenes/tiny", **kwargs):
    module, *flags = args
    return launch(
        module, *flags, f"--dataset={dataset}", f"--data_dir={data_dir}", timeout=600, **kwargs
    )


@pytest.mark.slow
def test_train_writes_everything_it_promises(tiny_scenes_dir, tmp_path):
    workdir = tmp_path / "run"
    result = _launch(
        [
            "experiments.train",
            f"--workdir={workdir}",
            "--steps=6",
            "--checkpoint_every=3",
            "--eval_every=3",
            "--num_figures=2",
            *TINY_FLAGS,
        ],
        tiny_scenes_dir,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    # The hypernetwork generates the 20/10/20 banks of 3x3 filters (and biases) linearly
    # from the 6 global parameters; the first bank reads the recipe's local input.
    channels = registry.make_model("global_local", **recipe.ARCHITECTURE).local_in_channels
    generated = sum(
        9 * c_in * c_out + c_out for c_in, c_out in [(channels, 20), (20, 10), (10, 20)]
    )
    assert f"parameters hypernet: {7 * generated:,}" in result.stdout
    assert "--steps=6: 0 warm-up steps (the recipe's 5%)" in result.stdout
    assert "--steps=6" in (workdir / "flags.txt").read_text()
    assert "--warmup_steps=0" in (workdir / "flags.txt").read_text()  # as it trained
    # The flow the dataset was built with, for an export's runtime to compute the same.
    assert json.loads((workdir / "dataset_flow.json").read_text())["estimator"] == "dis"
    records = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
    train_records = [r for r in records if r["split"] == "train"]
    assert [r["step"] for r in train_records] == [2, 4, 6]
    for key in (
        "loss",
        "depth_l1",
        "smoothness",
        "epipolar",  # the main job's default weight is 0.1
        "learning_rate",
        "steps_per_sec",
        "examples_per_sec",
    ):
        assert all(np.isfinite(r[key]) for r in train_records), key
    assert [r["step"] for r in records if r["split"] == "test"] == [3, 6]
    assert list((workdir / "tensorboard").glob("events.out.tfevents.*"))
    assert sorted(p.name for p in (workdir / "checkpoints").iterdir() if p.name.isdigit()) == [
        "3",
        "6",
    ]
    report = json.loads((workdir / "eval" / "metrics.json").read_text())
    # The final table carries the references, on the same 16 pairs and the same flow.
    methods = ["global_local", "dataset_mean", "oracle_pair_median", "sfm_flow"]
    assert list(report["methods"]) == methods
    for name in methods:
        assert report["methods"][name]["abs_inv"]["count"] == 16, name
    assert report["flow_source"] == "estimated"
    assert report["abs_inv_vs_dataset_mean"]["dataset_mean"] == 1.0
    assert "||t|| = 1" in report["protocol"] and report["step"] == 6
    table = (workdir / "eval" / "table.md").read_text()
    assert "| global_local |" in table and "| dataset_mean |" in table
    assert "| oracle_pair_median — per-pair oracle constant (sees the truth) |" in table
    (sfm_row,) = [
        line
        for line in table.splitlines()
        if line.startswith("| sfm_flow — classical pipeline on the same flow (no training) |")
    ]
    assert sfm_row.endswith(f"| {report['abs_inv_vs_dataset_mean']['sfm_flow']:.2f}× |")
    assert "Abs-Inv ÷ dataset_mean" in table
    rows = (workdir / "eval" / "per_example_global_local.csv").read_text().splitlines()
    assert rows[0].startswith("id,") and len(rows) == 17
    assert len(list((workdir / "eval" / "figures").glob("*.png"))) == 2
    assert "Abs-Inv" in result.stdout  # the printed table

    # the same command on a different architecture is refused, naming the flag
    refused = _launch(
        ["experiments.train", f"--workdir={workdir}", "--steps=6", "--global_dim=3", *TINY_FLAGS],
        tiny_scenes_dir,
    )
    assert refused.returncode != 0 and "global_dim" in refused.stderr

    inspected = _launch(
        ["experiments.inspect_filters", f"--workdir={workdir}", "--num_pairs=4", "--num_figures=2"],
        tiny_scenes_dir,
    )
    assert inspected.returncode == 0, inspected.stderr[-3000:]
    assert "Spearman" in inspected.stdout
    similarity = json.loads((workdir / "filters" / "similarity.json").read_text())
    assert len(similarity["global_params"]) == 4 and len(similarity["filter_similarity"]) == 4
    assert len(list((workdir / "filters").glob("*.png"))) == 2

    # evaluate re-runs on the workdir alone; a subset of another split goes to its own folder
    evaluated = _launch(
        [
            "experiments.evaluate",
            f"--workdir={workdir}",
            "--num_figures=0",
            "--split=train",
            "--max_examples=2",
        ],
        tiny_scenes_dir,
    )
    assert evaluated.returncode == 0, evaluated.stderr[-3000:]
    subset = json.loads((workdir / "eval_train_first2" / "metrics.json").read_text())
    assert subset["methods"]["global_local"]["abs_inv"]["count"] == 2
    assert json.loads((workdir / "eval" / "metrics.json").read_text()) == report

    # flags.txt holds only gld's flags and relaunches the run: nothing left to train, and
    # the final evaluation of step 6 is not done again
    flags_text = (workdir / "flags.txt").read_text()
    assert (
        "--steps=6" in flags_text and "grain" not in flags_text and "--verbosity" not in flags_text
    )
    written = (workdir / "eval" / "metrics.json").stat().st_mtime_ns
    relaunched = _launch(
        ["experiments.train", f"--flagfile={workdir / 'flags.txt'}"], tiny_scenes_dir
    )
    assert relaunched.returncode == 0, relaunched.stderr[-3000:]
    assert "resumed from step 6" in relaunched.stdout
    assert (
        f"{workdir / 'eval' / 'metrics.json'} already scores step 6: not evaluated again"
        in relaunched.stdout
    )
    assert (workdir / "eval" / "metrics.json").stat().st_mtime_ns == written


@pytest.mark.parametrize(
    ("flag", "message"),
    [
        ("--learning_rate=-0.01", "--learning_rate must be above 0"),
        ("--log_every=0", "flag --log_every=0"),
        ("--bank_channels=20,0,20", "--bank_channels must be at least 1 (every item)"),
    ],
)
def test_a_bad_value_stops_the_trainer_before_anything_is_written(
    tiny_scenes_dir, tmp_path, flag, message
):
    workdir = tmp_path / "run"
    result = _launch(["experiments.train", f"--workdir={workdir}", flag], tiny_scenes_dir)
    assert result.returncode != 0
    assert message in result.stderr
    assert not workdir.exists()


def test_an_epipolar_term_asked_of_a_model_without_a_pose_stops_the_trainer(
    tiny_scenes_dir, tmp_path
):
    workdir = tmp_path / "run"
    flags = ["experiments.train", f"--workdir={workdir}", "--global_dim=4"]
    result = _launch([*flags, "--epipolar_weight=0.1"], tiny_scenes_dir)
    assert result.returncode != 0
    assert "--epipolar_weight needs global parameters" in result.stderr
    assert not workdir.exists()


@pytest.mark.slow  # four launches in subprocesses: ~30 s of CPU
def test_a_relaunch_keeps_the_workdirs_architecture_and_the_probe_reads_its_g(
    tiny_scenes_dir, tmp_path
):
    workdir = tmp_path / "run"
    common = ["experiments.train", f"--workdir={workdir}", "--eval_every=0", "--nofinal_eval"]
    paper_module = ["--encoder_norm=none", "--use_image_pair"]
    first = _launch([*common, "--steps=3", *paper_module, *TINY_FLAGS], tiny_scenes_dir)
    assert first.returncode == 0, first.stderr[-3000:]
    # The trainer's defaults (instance norm, flow only) differ from this run's.
    again = _launch([*common, "--steps=5", *TINY_FLAGS], tiny_scenes_dir)
    assert again.returncode == 0, again.stderr[-3000:]
    assert "encoder_norm=none" in again.stdout and "use_image_pair=True" in again.stdout
    assert "resumed from step 3" in again.stdout
    stored = workdir_lib.stored_architecture(workdir)
    assert (stored["encoder_norm"], stored["use_image_pair"]) == ("none", True)
    # A flag given still asks for another architecture, which the workdir refuses.
    other = _launch([*common, "--steps=7", "--encoder_norm=instance", *TINY_FLAGS], tiny_scenes_dir)
    assert other.returncode != 0
    assert "--encoder_norm='none' there, 'instance' now" in other.stderr

    # The probe reads g as a pose for this run (trained with the epipolar term), even
    # without the MLP probe.
    probed = _launch(
        ["experiments.probe", f"--workdir={workdir}", "--nopose_probe"], tiny_scenes_dir
    )
    assert probed.returncode == 0, probed.stderr[-3000:]
    report = json.loads((workdir / "eval" / "probe.json").read_text())
    assert set(report["pose_probe"]) == {"global_params_read_as_pose"}
    errors = report["pose_probe"]["global_params_read_as_pose"]
    assert 0 <= errors["translation_deg"] <= 90 and errors["rotation_deg"] >= 0
    assert "global_params_read_as_pose: rotation" in probed.stdout


def test_a_multi_process_run_whose_peers_never_join_says_what_to_check(tmp_path):
    import socket

    with socket.socket() as probe:
        probe.bind(("localhost", 0))
        port = probe.getsockname()[1]
    workdir = tmp_path / "run"
    flags = ["--num_processes=2", "--process_id=0", f"--coordinator_address=localhost:{port}"]
    result = _launch(
        ["experiments.train", f"--workdir={workdir}", *flags, "--distributed_timeout=2"],
        tmp_path / "data",
    )
    assert result.returncode == 3
    assert f"did not all join at localhost:{port} within 2 s" in result.stderr
    assert not workdir.exists()


@pytest.mark.slow  # a subprocess killed mid-run; the in-process resume test is in the default run
def test_a_run_killed_with_sigkill_resumes_to_the_same_parameters(tiny_scenes_dir, tmp_path):
    common = [
        "experiments.train",
        "--steps=60",
        "--checkpoint_every=5",
        "--eval_every=0",
        "--final_eval=false",
        *TINY_FLAGS,
    ]
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=str(REPO_ROOT))
    killed_dir = tmp_path / "killed"
    command = [
        sys.executable,
        "-m",
        *common,
        f"--workdir={killed_dir}",
        "--dataset=gld_scenes/tiny",
        f"--data_dir={tiny_scenes_dir}",
    ]
    process = subprocess.Popen(
        command, env=env, cwd=REPO_ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    checkpoints = killed_dir / "checkpoints"
    deadline = time.time() + 300
    while time.time() < deadline and process.poll() is None:
        if checkpoints.exists() and any(p.name.isdigit() for p in checkpoints.iterdir()):
            break
        time.sleep(0.05)
    process.send_signal(signal.SIGKILL)
    process.wait()
    steps_done = [int(p.name) for p in checkpoints.iterdir() if p.name.isdigit()]
    assert steps_done and max(steps_done) < 60, "the run was not interrupted part-way"

    resumed = _launch([*common, f"--workdir={killed_dir}"], tiny_scenes_dir)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "resumed from step" in resumed.stdout
    straight = _launch([*common, f"--workdir={tmp_path / 'straight'}"], tiny_scenes_dir)
    assert straight.returncode == 0, straight.stderr[-3000:]

    _, resumed_vars, _ = workdir_lib.load_trained(killed_dir)
    _, straight_vars, _ = workdir_lib.load_trained(tmp_path / "straight")
    jax.tree_util.tree_map(
        lambda a, b: np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7),
        resumed_vars,
        straight_vars,
    )


@pytest.mark.parametrize("method", ["triangulation_gt_pose"])
def test_evaluate_runs_a_classical_baseline(tiny_scenes_dir, tmp_path, method):
    workdir = tmp_path / method
    result = _launch(
        [
            "experiments.evaluate",
            f"--method={method}",
            f"--workdir={workdir}",
            "--flow_source=gt",
            "--num_figures=1",
            "--nosfm_flow",
        ],
        tiny_scenes_dir,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((workdir / "eval_flow-gt" / "metrics.json").read_text())
    assert list(report["methods"]) == [method, "dataset_mean", "oracle_pair_median"]
    exact = report["methods"][method]["abs_inv"]["mean"]
    mean_baseline = report["methods"]["dataset_mean"]["abs_inv"]["mean"]
    # ground-truth flow and pose: triangulation is near exact, far better than the mean
    assert exact < 0.1 * mean_baseline


@pytest.mark.slow
def test_evaluate_scores_stored_predictions_and_refuses_a_folder_missing_one(
    tiny_scenes, tiny_scenes_dir, tmp_path
):
    folder = tmp_path / "predictions"
    folder.mkdir()
    source = tiny_scenes.as_data_source("test")
    for batch in input_pipeline.eval_batches(source, batch_size=16, flow_source="gt"):
        for example_id, depth in zip(batch["id"], batch["depth"], strict=True):
            np.save(folder / f"{stored_predictions.file_stem(example_id)}.npy", depth)
    workdir = tmp_path / "scored"
    result = _launch(
        ["experiments.evaluate", f"--predictions={folder}", f"--workdir={workdir}"],
        tiny_scenes_dir,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((workdir / "eval" / "metrics.json").read_text())
    assert list(report["methods"]) == [
        "stored_predictions",
        "dataset_mean",
        "oracle_pair_median",
        "sfm_flow",
    ]
    assert report["methods"]["stored_predictions"]["abs_inv"]["mean"] == 0.0
    assert report["methods"]["dataset_mean"]["abs_inv"]["mean"] > 0.01
    assert "| stored_predictions | 0.0000 ± 0.0000 |" in result.stdout

    missing = sorted(folder.iterdir())[3]
    missing.unlink()
    refused_dir = tmp_path / "refused"
    refused = _launch(
        ["experiments.evaluate", f"--predictions={folder}", f"--workdir={refused_dir}"],
        tiny_scenes_dir,
    )
    assert refused.returncode != 0
    assert f"without a <name>.npy or <name>.png: {missing.stem}" in refused.stderr
    assert not refused_dir.exists()


def test_evaluate_refuses_the_files_resolution_without_demon_files(tiny_scenes_dir, tmp_path):
    workdir = tmp_path / "refused"
    result = _launch(
        [
            "experiments.evaluate",
            "--method=dataset_mean",
            "--truth_resolution=file",
            f"--workdir={workdir}",
        ],
        tiny_scenes_dir,
    )
    assert result.returncode != 0
    assert (
        "--truth_resolution=file reads the ground truth from DeMoN's HDF5 files by example "
        "id; gld_scenes/tiny is not a demon/* dataset" in result.stderr
    )
    assert not workdir.exists()


def _write_custom_file(path, scenes: int) -> None:
    sys.path.insert(0, str(REPO_ROOT / "tests" / "data"))
    import demon_files

    rng = np.random.default_rng(0)
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as h5_file:
        for index in range(scenes):
            demon_files.write_scene(h5_file, f"s{index}", demon_files.moving_views(rng, 2, 48, 64))


@pytest.mark.slow
def test_a_dataset_with_one_split_serves_what_needs_only_that_split(tmp_path):
    train_only, test_only = tmp_path / "train_only", tmp_path / "test_only"
    _write_custom_file(train_only / "custom_train.h5", scenes=4)
    _write_custom_file(test_only / "custom_test.h5", scenes=2)

    def launch(args, manual_dir, workdir):
        return _launch(
            [*args, f"--manual_dir={manual_dir}", f"--workdir={workdir}"],
            tmp_path / f"data_{manual_dir.name}",
            dataset="demon/custom",
        )

    trained = launch(
        ["experiments.train", "--steps=3", "--eval_every=0", "--nofinal_eval", *TINY_FLAGS],
        train_only,
        tmp_path / "trained",
    )
    assert trained.returncode == 0, trained.stderr[-3000:]
    assert "4 train pairs" in trained.stdout
    refused = launch(["experiments.train", *TINY_FLAGS], train_only, tmp_path / "refused")
    assert refused.returncode != 0
    assert "no test split to evaluate on" in refused.stderr
    assert not (tmp_path / "refused").exists()

    oracle = launch(
        ["experiments.evaluate", "--method=oracle_pair_median", "--num_figures=0"],
        test_only,
        tmp_path / "oracle",
    )
    assert oracle.returncode == 0, oracle.stderr[-3000:]
    # A demon/* dataset is scored at its files' resolution by default (DeMoN's protocol).
    report = json.loads((tmp_path / "oracle" / "eval_truth-file" / "metrics.json").read_text())
    assert report["methods"]["oracle_pair_median"]["abs_inv"]["count"] == 2
    # No training split: the classical pipeline's failed pairs fall back to a fixed constant.
    assert report["methods"]["sfm_flow"]["abs_inv"]["count"] == 2
    assert report["sfm_flow_fallback"] == "a fixed constant (no training split)"
    assert "no training split: no dataset-mean row" in oracle.stdout
    mean = launch(["experiments.evaluate", "--method=dataset_mean"], test_only, tmp_path / "mean")
    assert mean.returncode != 0
    assert "--method=dataset_mean is fitted on the train split" in mean.stderr


# Two launches at DeMoN's 256x192: ~3 minutes on the 2-core machine. The same fallback,
# fast, on the library: tests/gld/evaluation/test_evaluation_run.py.
@pytest.mark.slow
def test_the_final_evaluation_of_a_demon_dataset_is_demons_protocol_or_says_why_not(tmp_path):
    manual_dir, data_dir, workdir = tmp_path / "manual", tmp_path / "data", tmp_path / "run"
    _write_custom_file(manual_dir / "custom_train.h5", scenes=2)
    _write_custom_file(manual_dir / "custom_test.h5", scenes=2)
    train = ["experiments.train", f"--workdir={workdir}", "--steps=3", "--eval_every=0"]
    train += ["--num_figures=0", *TINY_FLAGS]
    trained = _launch([*train, f"--manual_dir={manual_dir}"], data_dir, dataset="demon/custom")
    assert trained.returncode == 0, trained.stderr[-3000:]
    # As experiments.evaluate scores it by default: against the files' depth (64x48).
    report = json.loads((workdir / "eval_truth-file" / "metrics.json").read_text())
    assert report["truth_resolution"] == "file" and report["truth_resolutions"] == {"64x48": 2}
    assert report["records_protocol"]["image_decoder"] == "demon"
    assert "not DeMoN's protocol" not in report["protocol"]
    assert not (workdir / "eval").exists()

    # Relaunched finished, it does not evaluate again.
    again = _launch(train, data_dir, dataset="demon/custom")
    assert again.returncode == 0, again.stderr[-3000:]
    assert "already scores step 3: not evaluated again" in again.stdout

    # The files gone at the end of a run (one more step): scored at the records'
    # resolution rather than lost, saying so in one line and in the stamp, with the
    # command to score it later.
    manual_dir.rename(tmp_path / "elsewhere")
    resumed = _launch([*train, "--steps=4"], data_dir, dataset="demon/custom")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    command = (
        f"python -m experiments.evaluate --workdir={workdir} --data_dir={data_dir} "
        "--manual_dir=<the folder of the DeMoN files>"
    )
    (line,) = [text for text in resumed.stdout.splitlines() if "not by DeMoN's protocol" in text]
    assert line.startswith("demon/custom/2.0.0 test split: scored at the records' 256x192, not")
    assert line.endswith(f"to score it by DeMoN's protocol: {command}")
    fallback = json.loads((workdir / "eval" / "metrics.json").read_text())
    assert fallback["truth_resolution"] == "record" and fallback["step"] == 4
    assert (
        "not DeMoN's protocol: the DeMoN files of the test split were not at hand (score by "
        f"it: {command})" in fallback["protocol"]
    )
    assert fallback["protocol"] in (workdir / "eval" / "table.md").read_text()


@pytest.mark.slow  # two trainings and a diagnosis in subprocesses (about 90 s alone)
def test_diagnose_self_supervised_launcher(tiny_scenes_dir, tmp_path):
    workdir = tmp_path / "struct2depth"
    trained = _launch(
        [
            "experiments.train",
            "--model=struct2depth",
            f"--workdir={workdir}",
            "--steps=2",
            "--batch_size=4",
            "--log_every=1",
            "--warmup_steps=1",
            "--nofinal_eval",
        ],
        tiny_scenes_dir,
    )
    assert trained.returncode == 0, trained.stderr[-3000:]
    missing = _launch(
        ["experiments.diagnose_self_supervised", f"--workdirs={workdir},{tmp_path / 'none'}"],
        tiny_scenes_dir,
    )
    assert missing.returncode != 0 and "no such directory" in missing.stderr
    assert not (workdir / "eval" / "self_supervised_diagnosis.json").exists()

    result = _launch(
        ["experiments.diagnose_self_supervised", f"--workdirs={workdir}"], tiny_scenes_dir
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads((workdir / "eval" / "self_supervised_diagnosis.json").read_text())
    assert report["summary"]["pairs"] == 16
    assert set(report["photometric_at_truth"]) == {
        "truth",
        "flat depth, true pose",
        "true depth, half translation",
        "true depth, twice the translation",
        "true depth, reversed translation",
    }
    assert "at the truth's scale" in result.stdout
