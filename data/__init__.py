"""gld's TFDS dataset builders, chosen by name: `gld_scenes/small`, `demon/sun3d`, ...

Each builder lives in `data/<name>/<name>_dataset_builder.py` as class `Builder`
(the TFDS convention). Launchers call `prepare()`, which builds a dataset on first
use and returns the builder. The builders write array_record by default, so the
plain TFDS API works without TensorFlow too once the builder module is imported:

    import data.gld_scenes.gld_scenes_dataset_builder  # registers `gld_scenes`
    tfds.builder("gld_scenes/tiny", data_dir="datasets").download_and_prepare()

(`tfds build` does not: TFDS's command line imports TensorFlow at start-up, so
`python -m data.build` is the command line.)
"""

from __future__ import annotations

import importlib
import os
from pathlib import Path

import tensorflow_datasets as tfds

# Dataset name -> module holding its `Builder` class.
DATASETS = {
    "gld_scenes": "data.gld_scenes.gld_scenes_dataset_builder",
    "demon": "data.demon.demon_dataset_builder",
}

DEFAULT_DATA_DIR = os.environ.get("GLD_DATA_DIR", "datasets")

# The builders' default file format. TFDS's own default, TFRecord, needs TensorFlow to
# write; array_record does not, and gives the random access the input pipeline uses.
FILE_FORMAT = "array_record"


def builder_class(name: str) -> type[tfds.core.GeneratorBasedBuilder]:
    """The builder class registered under a dataset name (without config)."""
    if name not in DATASETS:
        raise ValueError(f"unknown dataset {name!r}; valid: {sorted(DATASETS)}")
    return importlib.import_module(DATASETS[name]).Builder


def parse_name(dataset: str) -> tuple[str, str]:
    """'gld_scenes/small' -> ('gld_scenes', 'small'); the config must be given."""
    name, _, config = dataset.partition("/")
    cls = builder_class(name)
    configs = [c.name for c in cls.BUILDER_CONFIGS]
    if config not in configs:
        raise ValueError(
            f"unknown config {config!r} of dataset {name!r}; valid: "
            + ", ".join(f"{name}/{c}" for c in configs)
        )
    return name, config


def get_builder(
    dataset: str, data_dir: str | os.PathLike | None = None, **builder_kwargs
) -> tfds.core.GeneratorBasedBuilder:
    """The (possibly not yet built) builder of `dataset` ('name/config') under `data_dir`."""
    name, config = parse_name(dataset)
    data_dir = Path(data_dir or DEFAULT_DATA_DIR)
    return builder_class(name)(config=config, data_dir=str(data_dir), **builder_kwargs)


def prepare(
    dataset: str,
    data_dir: str | os.PathLike | None = None,
    manual_dir: str | os.PathLike | None = None,
    **builder_kwargs,
) -> tfds.core.GeneratorBasedBuilder:
    """Builds `dataset` if it is not built yet and returns its builder."""
    builder = get_builder(dataset, data_dir, **builder_kwargs)
    download_config = tfds.download.DownloadConfig(
        manual_dir=str(manual_dir) if manual_dir else None
    )
    builder.download_and_prepare(download_config=download_config)
    return builder
