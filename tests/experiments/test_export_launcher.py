"""The export launcher (python -m experiments.export) on a tiny trained workdir."""

import json
import shutil
import subprocess
import zipfile

import global_local_reference as reference
import numpy as np
import pytest
from conftest import launch

from gld.inference import workdir_export
from gld.inference.deploy import DeployedModel
from gld.runs import workdir as workdir_lib


def _launch(*flags: str) -> subprocess.CompletedProcess:
    return launch("experiments.export", *flags)


def test_exports_the_latest_checkpoint_at_the_training_resolution(trained_workdir, tmp_path):
    output = tmp_path / "export" / "model.gldx"
    completed = _launch(f"--workdir={trained_workdir}", f"--output={output}")
    assert completed.returncode == 0, completed.stderr[-3000:]
    assert f"wrote {output}" in completed.stdout

    model, variables, config = workdir_lib.load_trained(trained_workdir)
    deployed = DeployedModel.load(output)
    metadata = deployed.metadata
    assert (deployed.height, deployed.width) == (config.height, config.width) == (48, 64)
    assert metadata["source"]["workdir"] == str(trained_workdir.absolute())
    assert metadata["source"]["step"] == 2 and metadata["source"]["dataset"] == "gld_scenes/tiny"
    assert metadata["model_config"]["encoder_channels"] == config.model_config["encoder_channels"]
    rng = np.random.default_rng(0)
    image1 = rng.integers(0, 256, (2, 48, 64, 3), dtype=np.uint8)
    image2 = rng.integers(0, 256, (2, 48, 64, 3), dtype=np.uint8)
    flow = rng.normal(0, 2, (2, 48, 64, 2)).astype(np.float32)
    # The trained network, written out in numpy, on value / 255 - 0.5.
    expected = reference.global_local(
        model, variables, image1 / 255.0 - 0.5, image2 / 255.0 - 0.5, flow
    )
    np.testing.assert_allclose(deployed(image1, image2, flow), expected["depth"], rtol=1e-4)
    # The flow the runtime computes is the one the run's dataset was built with, DIS.
    assert metadata["flow"]["estimator"] == "dis" and metadata["flow"]["preset"] == "medium"
    assert "flow: estimator dis" in completed.stdout


def test_bad_flags_are_refused_before_anything_is_written(trained_workdir, tmp_path):
    output = tmp_path / "model.gldx"
    completed = _launch(f"--workdir={trained_workdir}", f"--output={output}", "--platforms=gpu")
    assert completed.returncode != 0
    assert "unknown platform(s) ['gpu']" in completed.stderr
    with pytest.raises(ValueError, match=r"no checkpoint of step 5 .* available: \[2\]"):
        workdir_export.export_workdir(trained_workdir, output, step=5)
    with pytest.raises(ValueError, match="'vmap' needs a fixed batch size"):
        workdir_export.export_workdir(trained_workdir, output, formulation="vmap")
    with pytest.raises(FileNotFoundError, match="config.json"):
        workdir_export.export_workdir(tmp_path / "nowhere", output)
    assert not output.exists()
    # A fixed batch for the GPU formulation is accepted (lowered here for CPU).
    metadata = workdir_export.export_workdir(
        trained_workdir, output, formulation="vmap", batch_size=1, step=2
    )
    assert metadata["batch_size"] == 1 and metadata["formulation"] == "vmap"
    with zipfile.ZipFile(output) as archive:
        assert json.loads(archive.read("metadata.json"))["source"]["step"] == 2


def test_a_workdir_without_a_checkpoint_is_named_in_one_line(trained_workdir, tmp_path):
    """The launchers that load a trained run say which workdir holds no checkpoint (or
    not the step asked for, or a formulation export refuses), in one line with the usage
    status, and write nothing."""
    empty = tmp_path / "untrained"
    (empty / "checkpoints").mkdir(parents=True)
    shutil.copy(trained_workdir / "config.json", empty / "config.json")
    before = sorted(path.relative_to(empty) for path in empty.rglob("*"))
    output, online = tmp_path / "model.gldx", tmp_path / "online"
    checkpoints = empty / "checkpoints"
    for module, flags, line in [
        ("experiments.export", [f"--workdir={empty}", f"--output={output}"], None),
        (
            "experiments.online",
            [f"--pretrained={empty}", f"--workdir={online}", "--frames=2"],
            None,
        ),
        (
            "experiments.export",
            [f"--workdir={empty}", f"--output={output}", "--step=5"],
            f"no checkpoint of step 5 in {checkpoints}; available: []",
        ),
        (
            "experiments.export",
            [f"--workdir={empty}", f"--output={output}", "--formulation=vmap"],
            "--formulation=vmap: formulation 'vmap' needs a fixed batch size",
        ),
    ]:
        completed = launch(module, *flags)
        assert completed.returncode == 2, (module, completed.stderr[-3000:])
        last = completed.stderr.splitlines()[-1]
        if line is None:
            assert last == f"no checkpoint in {checkpoints}"
        else:
            assert last.startswith(line), (flags, last)
        assert "Traceback" not in completed.stderr, module
    assert not output.exists() and not online.exists()
    assert sorted(path.relative_to(empty) for path in empty.rglob("*")) == before


def test_the_runtime_flow_comes_from_the_record_or_the_flag(trained_workdir, tmp_path):
    output = tmp_path / "model.gldx"
    given = workdir_export.export_workdir(trained_workdir, output, flow="farneback")
    assert given["flow"]["estimator"] == "farneback"
    # A run without the record (trained before it was written) needs the flag.
    old = tmp_path / "old_run"
    shutil.copytree(trained_workdir, old)
    (old / workdir_export.FLOW_RECORD).unlink()
    completed = _launch(f"--workdir={old}", f"--output={tmp_path / 'old.gldx'}")
    assert completed.returncode == 2
    assert "does not record which flow its dataset was built with" in completed.stderr
    assert "--flow=dis" in completed.stderr and "Traceback" not in completed.stderr
    completed = _launch(f"--workdir={old}", f"--output={output}", "--flow=dis_slow")
    assert completed.returncode == 2 and "unknown flow estimator 'dis_slow'" in completed.stderr
    assert not (tmp_path / "old.gldx").exists()
