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


# TrainConfig fields set by the training flags below (shared by train and compare).
TRAINING_FLAGS = (
    "batch_size",
    "steps",
    "learning_rate",
    "lr_schedule",
    "warmup_steps",
    "depth_weight",
    "smoothness_weight",
    "gt_pixels",
    "fixed_sparse_pixels",
    "flow",
    "augment",
    "seed",
    "log_every",
    "eval_every",
    "eval_examples",
    "checkpoint_every",
    "worker_count",
)


def define_training_flags(
    *,
    steps: int,
    eval_every: int,
    learning_rate: float = 1e-4,
    lr_schedule: str = "constant",
    warmup_steps: int = 0,
) -> None:
    """The run flags every training launcher shares (budget, loss, data order, logging).

    The optimiser defaults are the paper's (Adam 1e-4, constant) unless a launcher
    gives its own (the main job's recipe in `experiments.train`)."""
    flags.DEFINE_integer("gt_pixels", 1, "Supervised pixels per image (1, 4, 16, 64); 0 = dense.")
    flags.DEFINE_bool("fixed_sparse_pixels", False, "Keep the same supervised pixels every epoch.")
    flags.DEFINE_integer("batch_size", 16, "Global batch size.")
    flags.DEFINE_integer("steps", steps, "Training steps (the paper: 94000 at 256x192).")
    flags.DEFINE_float("learning_rate", learning_rate, "Adam (peak) learning rate.")
    flags.DEFINE_enum(
        "lr_schedule", lr_schedule, ["constant", "cosine"], "constant (the paper) or cosine."
    )
    flags.DEFINE_integer(
        "warmup_steps", warmup_steps, "Linear warm-up steps of the cosine schedule."
    )
    flags.DEFINE_float("depth_weight", 5.0, "Weight of the sparse L1 inverse-depth loss.")
    flags.DEFINE_float("smoothness_weight", 2.0, "Weight of the edge-aware smoothness loss.")
    flags.DEFINE_bool("augment", True, "Rotate-180 / mirror-x augmentation.")
    flags.DEFINE_integer("seed", 0, "Seed of initialisation, data order, augmentation, sparsity.")
    flags.DEFINE_integer("log_every", 50, "Steps between metrics.jsonl / TensorBoard records.")
    flags.DEFINE_integer(
        "eval_every", eval_every, "Steps between evaluations on the test split (0: off)."
    )
    flags.DEFINE_integer(
        "eval_examples", 0, "Periodic evaluation on the first N test pairs; 0 = all."
    )
    flags.DEFINE_integer("checkpoint_every", 250, "Steps between checkpoints.")
    flags.DEFINE_integer("worker_count", 0, "grain worker processes for the input pipeline.")


def training_options() -> dict:
    """The TrainConfig fields given by the training flags."""
    return {name: FLAGS[name].value for name in TRAINING_FLAGS}


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
