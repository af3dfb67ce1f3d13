"""gld's TFDS dataset builders, chosen by name: `gld_scenes/small`, `demon/sun3d`, ...

Each builder lives in `data/<name>/<name>_dataset_builder.py` as class `Builder`
(the TFDS convention). Launchers call `prepare()`, which builds a dataset on first
use and returns the builder. The builders write array_record by default, so the
plain TFDS API works without TensorFlow too once the builder module is imported:

    import data.gld_scenes.gld_scenes_dataset_builder  # registers `gld_scenes`
    tfds.builder("gld_scenes/tiny", data_dir="datasets").download_and_prepare()

(`tfds build` does not: TFDS's command line imports TensorFlow at start-up, so
`python -m data.build` is the command line.)

A built dataset is reused, never silently rebuilt, and never reused for other input:
a builder that reads a manual directory records the fingerprints of the files it
read (`data.sources`), and every builder with options records them per split
(`builder.info.metadata["build_options"]`). `prepare()` compares them with what it
is given and refuses a mismatch; `rebuild=True` builds again (see `prepare`).
"""

from __future__ import annotations

import importlib
import logging
import os
import shutil
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import tensorflow_datasets as tfds

from data import sources
from gld.arguments import ArgumentError

_LOGGER = logging.getLogger(__name__)

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
        raise ArgumentError(f"--dataset: unknown dataset {name!r}; valid: {sorted(DATASETS)}")
    return importlib.import_module(DATASETS[name]).Builder


def parse_name(dataset: str) -> tuple[str, str]:
    """'gld_scenes/small' -> ('gld_scenes', 'small'); the config must be given."""
    name, _, config = dataset.partition("/")
    cls = builder_class(name)
    configs = [c.name for c in cls.BUILDER_CONFIGS]
    if config not in configs:
        raise ArgumentError(
            f"--dataset={dataset}: unknown config {config!r} of dataset {name!r}; valid: "
            + ", ".join(f"{name}/{c}" for c in configs)
        )
    return name, config


def version(dataset: str) -> str:
    """The version a build of `dataset` ('name/config') has with this code, e.g. "2.0.0"
    (the config's own version, else its builder's)."""
    name, config = parse_name(dataset)
    cls = builder_class(name)
    return str(cls.builder_configs[config].version or cls.VERSION)


def get_builder(
    dataset: str, data_dir: str | os.PathLike | None = None, **builder_kwargs
) -> tfds.core.GeneratorBasedBuilder:
    """The (possibly not yet built) builder of `dataset` ('name/config') under `data_dir`."""
    name, config = parse_name(dataset)
    data_dir = Path(data_dir or DEFAULT_DATA_DIR)
    return builder_class(name)(config=config, data_dir=str(data_dir), **builder_kwargs)


def reuse_problems(
    builder: tfds.core.GeneratorBasedBuilder,
    manual_dir: str | os.PathLike | None,
    builder_kwargs: Mapping[str, Any],
) -> list[str]:
    """Why a built dataset does not match the input now given, one line per difference.

    Compared: every option given in `builder_kwargs` (None values leave an option to
    the build) that the builder records in `metadata["build_options"]`, against the
    value it was built with; and, when `manual_dir` is given and the builder reads one
    (it defines `source_files(manual_dir) -> {split: [paths]}`), the files it would
    read now against the recorded `metadata["sources"]` (`sources.changes`).

    Args:
      builder: a builder whose dataset is built (`builder.is_prepared()`).
      manual_dir: the manual directory now given, or None (not compared).
      builder_kwargs: the builder options now given.
    """
    metadata = builder.info.metadata or {}
    problems = []
    given = {key: value for key, value in builder_kwargs.items() if value is not None}
    if given and hasattr(builder, "build_options"):
        for split, recorded in sorted(metadata.get("build_options", {}).items()):
            current = builder.build_options(split)
            for key in sorted(given):
                if key in recorded and key in current and current[key] != recorded[key]:
                    problems.append(
                        f"{split} split: {key}={current[key]!r} given, built with "
                        f"{key}={recorded[key]!r}"
                    )
    if manual_dir is not None and hasattr(builder, "source_files"):
        recorded_sources = metadata.get("sources")
        if recorded_sources is None:
            _LOGGER.warning(
                "%s records no source files (built by an earlier gld); it cannot be checked "
                "against %s. Rebuild it (python -m data.build ... --rebuild) to record them.",
                builder.data_path,
                manual_dir,
            )
        else:
            current = sources.fingerprints(builder.source_files(Path(manual_dir).expanduser()))
            problems.extend(sources.changes(recorded_sources, current))
    return problems


def _rebuild(
    dataset: str,
    data_dir: str | os.PathLike | None,
    download_config: tfds.download.DownloadConfig,
    builder_kwargs: Mapping[str, Any],
) -> tfds.core.GeneratorBasedBuilder:
    """Builds `dataset` in a staging folder under `data_dir`, then puts it in place of
    the built one; a build that fails leaves the built dataset as it was."""
    root = Path(data_dir or DEFAULT_DATA_DIR)
    target = Path(get_builder(dataset, root, **builder_kwargs).data_path)
    root.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".rebuild-", dir=root))
    try:
        staged = get_builder(dataset, staging, **builder_kwargs)
        staged.download_and_prepare(download_config=download_config)
        if target.exists():
            target.rename(staging / "replaced")
        target.parent.mkdir(parents=True, exist_ok=True)
        Path(staged.data_path).rename(target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return get_builder(dataset, root, **builder_kwargs)


def prepare(
    dataset: str,
    data_dir: str | os.PathLike | None = None,
    manual_dir: str | os.PathLike | None = None,
    *,
    rebuild: bool = False,
    **builder_kwargs,
) -> tfds.core.GeneratorBasedBuilder:
    """Builds `dataset` if it is not built yet and returns its builder.

    A built dataset is reused when it matches what is given (`reuse_problems`): the
    files of `manual_dir`, if given, and the options in `builder_kwargs`. Without
    `manual_dir` it is reused as it is.

    Args:
      dataset: 'name/config', e.g. 'demon/custom'.
      data_dir: where built datasets live (default `DEFAULT_DATA_DIR`).
      manual_dir: the manual-download directory the builder reads, if it reads one.
      rebuild: build again even if built; the new build replaces the old one only
        once it has succeeded.
      **builder_kwargs: the builder's options.

    Raises:
      ValueError: the built dataset was made from other files or options than those
        given (each difference named), unless `rebuild`.
    """
    builder = get_builder(dataset, data_dir, **builder_kwargs)
    download_config = tfds.download.DownloadConfig(
        manual_dir=str(Path(manual_dir).expanduser()) if manual_dir else None
    )
    # (is_prepared() alone warns about a folder that does not exist yet.)
    prepared = builder.data_path.exists() and builder.is_prepared()
    if rebuild or not prepared:
        _check_manual_dir(builder, dataset, data_dir, manual_dir)
    if prepared:
        if rebuild:
            return _rebuild(dataset, data_dir, download_config, builder_kwargs)
        problems = reuse_problems(builder, manual_dir, builder_kwargs)
        if problems:
            raise ArgumentError(
                f"{dataset} in {builder.data_path} was built from other input than given:\n  "
                + "\n  ".join(problems)
                + f"\nTo replace it, build it again: python -m data.build --dataset={dataset} "
                f"--data_dir={data_dir or DEFAULT_DATA_DIR} --manual_dir={manual_dir or '...'} "
                "--rebuild (or data.prepare(..., rebuild=True)). To keep it, build into "
                "another --data_dir, or leave out --manual_dir and the build options to use "
                "it as it is."
            )
    builder.download_and_prepare(download_config=download_config)
    return builder


def _check_manual_dir(builder, dataset: str, data_dir, manual_dir) -> None:
    """A builder that reads files it cannot download needs their folder: the one given,
    else TFDS's default (`<data_dir>/downloads/manual`); raises ArgumentError, naming
    the flag, when that folder does not exist or is empty."""
    if not getattr(builder, "MANUAL_DOWNLOAD_INSTRUCTIONS", None):
        return
    hint = f"the README's section on {dataset.partition('/')[0]} says which files it reads"
    if manual_dir is not None:
        folder = Path(manual_dir).expanduser()
        if not folder.is_dir():
            raise ArgumentError(f"--manual_dir={manual_dir}: no such directory ({hint})")
        if not any(folder.iterdir()):
            raise ArgumentError(f"--manual_dir={manual_dir}: the directory is empty ({hint})")
        return
    default = Path(data_dir or DEFAULT_DATA_DIR) / "downloads" / "manual"
    if not default.is_dir() or not any(default.iterdir()):
        raise ArgumentError(
            f"--manual_dir: {dataset} is built from files you provide; give their folder "
            f"(the default, {default}, is missing or empty; {hint})"
        )
