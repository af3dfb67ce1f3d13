"""Flags and set-up shared by the launchers (train, evaluate, inspect_filters, compare)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from absl import flags

FLAGS = flags.FLAGS


def define_data_flags(default_dataset: str = "gld_scenes/small") -> None:
    flags.DEFINE_string(
        "dataset", default_dataset, "TFDS dataset with config, e.g. gld_scenes/small, demon/sun3d."
    )
    flags.DEFINE_string("data_dir", None, "Where built datasets live (default: ./datasets).")
    flags.DEFINE_string("manual_dir", None, "Manual-download dir (DeMoN .h5 files).")


def define_flow_source_flag() -> None:
    """--flow_source for launchers that use a trained workdir (default: the workdir's)."""
    from gld.config import FLOW_SOURCES

    flags.DEFINE_enum(
        "flow_source",
        None,
        list(FLOW_SOURCES),
        "Which flow the model is given (default: the workdir's; estimated for a method "
        "without training).",
    )


def _define(name: str, default: Any, help_text: str, choices: Sequence[str] | None) -> None:
    """One flag, typed by its choices or its default."""
    if choices:
        flags.DEFINE_enum(name, default, list(choices), help_text)
    elif isinstance(default, bool):
        flags.DEFINE_bool(name, default, help_text)
    elif isinstance(default, int):
        flags.DEFINE_integer(name, default, help_text)
    elif isinstance(default, float):
        flags.DEFINE_float(name, default, help_text)
    elif isinstance(default, list | tuple):
        flags.DEFINE_list(name, [str(value) for value in default], help_text)
    else:
        flags.DEFINE_string(name, default, help_text)


def define_training_flags(*, exclude: Sequence[str] = (), **defaults: Any) -> None:
    """A flag for every option of `gld.config.TrainConfig` (its help, choices and
    default) but `exclude`; `defaults` replaces a default for this launcher (the main
    job's recipe in `experiments.train`)."""
    from gld import config

    fields = [field for field in config.flag_fields() if field.name not in exclude]
    unknown = sorted(set(defaults) - {field.name for field in fields})
    if unknown:
        raise ValueError(f"no TrainConfig option(s) {unknown} to give a default")
    for field in fields:
        default = defaults.get(field.name, field.default)
        _define(field.name, default, field.metadata["help"], field.metadata["choices"])


def training_options() -> dict[str, Any]:
    """The TrainConfig fields given by this launcher's training flags."""
    from gld import config

    return {
        field.name: FLAGS[field.name].value for field in config.flag_fields() if field.name in FLAGS
    }


def define_architecture_flags() -> None:
    """A flag for every architecture option of the global-local model
    (`gld.model.architecture_options`: its default, help and choices)."""
    from gld import model

    for name, (default, help_text, choices) in model.architecture_options().items():
        _define(name, default, help_text, choices)


def architecture_options() -> dict[str, Any]:
    """The global-local model's constructor arguments from the architecture flags (lists
    as ints; an option left at None, like the speed-only formulation, is omitted)."""
    from gld import model

    values = {}
    for name, (default, _, _) in model.architecture_options().items():
        value = FLAGS[name].value
        if isinstance(default, list | tuple):
            value = [int(item) for item in value]
        if value is not None:
            values[name] = value
    return values


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
