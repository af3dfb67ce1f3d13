"""Flags and set-up shared by the launchers (train, evaluate, inspect_filters, compare)."""

from __future__ import annotations

import os
from pathlib import Path

from absl import flags

FLAGS = flags.FLAGS


def define_data_flags(default_dataset: str = "gld_scenes/small") -> None:
    flags.DEFINE_string(
        "dataset", default_dataset, "TFDS dataset with config, e.g. gld_scenes/small, demon/sun3d."
    )
    flags.DEFINE_string("data_dir", None, "Where built datasets live (default: ./datasets).")
    flags.DEFINE_string("manual_dir", None, "Manual-download dir (DeMoN .h5 files).")
    flags.DEFINE_enum("flow", "estimated", ["estimated", "gt"], "Which flow the model is given.")


def define_distributed_flags() -> None:
    flags.DEFINE_string("coordinator_address", None, "host:port of process 0 (multi-process).")
    flags.DEFINE_integer("num_processes", 1, "Number of JAX processes.")
    flags.DEFINE_integer("process_id", 0, "This process's index.")


def initialise() -> None:
    """Quiet library logs (unless --verbosity is given) and start multi-process JAX when
    --num_processes > 1 (before any device is touched)."""
    from absl import logging

    if not FLAGS["verbosity"].present:
        logging.set_verbosity(logging.WARNING)
    if "num_processes" in FLAGS and FLAGS.num_processes > 1:
        import jax

        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(
            coordinator_address=FLAGS.coordinator_address,
            num_processes=FLAGS.num_processes,
            process_id=FLAGS.process_id,
        )


def prepare_dataset(dataset: str | None = None):
    """Builds the dataset on first use and returns its TFDS builder."""
    import data

    return data.prepare(dataset or FLAGS.dataset, FLAGS.data_dir, FLAGS.manual_dir)


def dataset_resolution(builder) -> tuple[int, int]:
    """(height, width) of a built gld dataset."""
    height, width = builder.info.features["depth1"].shape
    return int(height), int(width)


def write_flags(workdir: str | os.PathLike) -> None:
    """Writes every flag of this run to workdir/flags.txt (a valid --flagfile)."""
    import jax

    if jax.process_index() != 0:
        return
    path = Path(workdir)
    path.mkdir(parents=True, exist_ok=True)
    (path / "flags.txt").write_text(FLAGS.flags_into_string())


def data_source(builder, split: str):
    """A split's random-access records, skipping fields no launcher reads."""
    from gld import input_pipeline

    return builder.as_data_source(split, decoders=input_pipeline.source_decoders())
