"""TFDS builder of DeMoN's HDF5 benchmarks: `demon/scenes11`, `sun3d`, `rgbd` and `custom`.

Every pair becomes a `gld.records` record at 256x192 (images INTER_AREA, depth
resampled by nearest neighbour, normalised intrinsics, raw metric depth and the
unnormalised relative pose, DIS flow and ground-truth flow), read as DeMoN's own
reader op reads it by default: its WebP decoding, its depth resampling, its pairs and
its order (records stored in the order DeMoN's reader gives them, not TFDS's key
hash; data/demon/README.md lists each option that departs from it). Damaged pairs are
skipped and counted by reason, pairs without a baseline apart from damage; the report
is printed and stored in the dataset's metadata (`builder.info.metadata
["build_report"]`), next to the options the records were built with
(`["build_options"]`: the protocol stamp) and the fingerprints of the files they were
built from (`["sources"]`, see `data.sources`; `data.prepare` refuses to reuse the
dataset for other files or options). Every input file is checked
(`reader.check_files`, and whether its images can be decoded as asked,
`reader.check_image_decoder`) before any split is built.

    data.prepare("demon/sun3d", data_dir, manual_dir="~/demon", strict=True)

Builder keyword arguments: `strict` (fail at the first damaged pair),
`max_bad_fraction` (fail when more of a split's pairs are damaged, default 0.05),
`verify_checksums` (check files against their published MD5 sums, default True),
`flow_estimator` (a `gld.flow.ESTIMATORS` name, or "flow_net:<workdir>" for a trained
flow network), `min_relative_baseline` (skip pairs whose baseline is at most this x
the median depth; default 1e-4 for train and 0 for test, so the test split keeps every
pair DeMoN evaluates), `depth_resampling` (`demon`, the default of every config:
DeMoN's INTER_NEAREST; `centred`: centre-aligned with hole filling, which keeps sparse
range readings) and `image_decoder` (`demon`, the default: libwebp as DeMoN's C++
reader, through the `webp` package, without which a build of lossy images is refused;
`opencv`: libwebp's defaults, as DeMoN's Python reader, an approximation).
"""

from __future__ import annotations

import dataclasses
import logging
from pathlib import Path
from typing import Any

import tensorflow_datasets as tfds

import data
from data import sources
from data.demon import checksums, images, pairs, reader
from gld import flow as flow_lib
from gld import records
from gld.arguments import ArgumentError
from gld.runs import trained_flow

_LOGGER = logging.getLogger(__name__)

_DEMON_URL = "https://lmb.informatik.uni-freiburg.de/data/demon/"

# One line of MANUAL_DOWNLOAD_INSTRUCTIONS, for an error.
MISSING_FILES_HINT = (
    f"DeMoN's files come from {_DEMON_URL}: testdata/<name>_test.tgz and "
    "traindata/<name>_train.tgz, unpacked; the README's DeMoN section lists them"
)


class MissingFilesError(ArgumentError, FileNotFoundError):
    """A split's DeMoN files are not in the manual directory (one line naming them)."""


MANUAL_DOWNLOAD_INSTRUCTIONS = f"""\
Put DeMoN's HDF5 files (Ummenhofer et al., CVPR 2017; research use only) in the
manual directory, e.g. `data.prepare("demon/sun3d", manual_dir=DIR)` or
`python -m experiments.train --dataset=demon/sun3d --manual_dir=DIR`.
They come from {_DEMON_URL} (DeMoN's datasets/download_testdata.sh and
download_traindata.sh fetch and unpack them):

  testdata/<name>_test.tgz   -> scenes11_test.h5, sun3d_test.h5, rgbd_test.h5
  traindata/scenes11_train.tgz -> scenes11_train.h5
  traindata/sun3d_train.tgz    -> sun3d_train_0.01m_to_0.1m.h5, sun3d_train_0.1m_to_0.2m.h5,
                                  sun3d_train_0.2m_to_0.4m.h5, sun3d_train_0.4m_to_0.8m.h5,
                                  sun3d_train_0.8m_to_1.6m.h5, sun3d_train_1.6m_to_infm.h5
  traindata/rgbd_bugfix_train.tgz -> rgbd_bugfix_10_to_20_3d_train.h5,
                                  rgbd_bugfix_10_to_20_handheld_train.h5,
                                  rgbd_bugfix_20_to_inf_3d_train.h5,
                                  rgbd_bugfix_20_to_inf_handheld_train.h5
  traindata/rgbd_train.tgz     -> rgbd_10_to_20_simple_train.h5, rgbd_20_to_inf_simple_train.h5
                                  (only these two; its other rgbd_*_train.h5 files leaked
                                  test samples and are refused)

Each config needs all files of a split; a split with none of its files is left out
(e.g. test files only, for evaluation). Files are checked against DeMoN's published
MD5 sums (traindata.md5, testdata.md5); pass verify_checksums=False to skip.

Config `custom` reads a robot's own recordings written by `python -m data.demon.convert`:
`custom_train.h5` / `custom_test.h5`, or several recordings named
`custom_train_<recording>.h5` / `custom_test_<recording>.h5`.
"""


# How the records of a split are ordered (`build_options`): as DeMoN's reader op gives
# them in its test phase (`pairs.generate`).
ORDER = "demon"


@dataclasses.dataclass(kw_only=True)
class DemonConfig(tfds.core.BuilderConfig):
    """Which files of the manual directory make each split (glob patterns when `custom`),
    and the depth resampling (`pairs.DEPTH_RESAMPLING`) its records default to."""

    train_files: tuple[str, ...] = ()
    test_files: tuple[str, ...] = ()
    globs: bool = False
    depth_resampling: str = pairs.DEFAULT_DEPTH_RESAMPLING


_SUN3D_TRAIN = tuple(
    f"sun3d_train_{band}.h5"
    for band in ("0.01m_to_0.1m", "0.1m_to_0.2m", "0.2m_to_0.4m", "0.4m_to_0.8m")
) + ("sun3d_train_0.8m_to_1.6m.h5", "sun3d_train_1.6m_to_infm.h5")
_RGBD_TRAIN = (
    "rgbd_bugfix_10_to_20_3d_train.h5",
    "rgbd_bugfix_10_to_20_handheld_train.h5",
    "rgbd_bugfix_20_to_inf_3d_train.h5",
    "rgbd_bugfix_20_to_inf_handheld_train.h5",
    "rgbd_10_to_20_simple_train.h5",
    "rgbd_20_to_inf_simple_train.h5",
)


class Builder(tfds.core.GeneratorBasedBuilder):
    """DeMoN's Scenes11, SUN3D and RGB-D SLAM benchmarks, and converted recordings."""

    VERSION = tfds.core.Version("2.0.0")
    RELEASE_NOTES = {
        "1.0.0": "Records at 256x192 with DIS flow and ground-truth flow.",
        "1.1.0": "DeMoN's protocol: the test split keeps small-baseline pairs (only "
        "||t|| < 1e-6 is skipped), depth resampled with OpenCV INTER_NEAREST; WebP decoded "
        "as DeMoN's C++ reader on request (image_decoder=demon).",
        "2.0.0": "DeMoN's protocol by default everywhere: WebP decoded as DeMoN's C++ reader "
        "(image_decoder=demon; other images than 1.1.0's), DeMoN's depth resampling for "
        "custom too (other depth than 1.1.0's where a recording is not 256x192), records "
        "stored in DeMoN's order (files as listed, scene groups reverse-sorted) instead of "
        "TFDS's key hash; pairs with ||t|| < 1e-6 counted apart from damage; the order "
        "stamped in build_options.",
    }
    MANUAL_DOWNLOAD_INSTRUCTIONS = MANUAL_DOWNLOAD_INSTRUCTIONS
    BUILDER_CONFIGS = [
        DemonConfig(
            name="scenes11",
            description="Synthetic ShapeNet scenes (DeMoN's Scenes11).",
            train_files=("scenes11_train.h5",),
            test_files=("scenes11_test.h5",),
        ),
        DemonConfig(
            name="sun3d",
            description="Indoor SUN3D sequences, DeMoN's baseline bands.",
            train_files=_SUN3D_TRAIN,
            test_files=("sun3d_test.h5",),
        ),
        DemonConfig(
            name="rgbd",
            description="TUM RGB-D SLAM sequences (bugfix training files).",
            train_files=_RGBD_TRAIN,
            test_files=("rgbd_test.h5",),
        ),
        DemonConfig(
            name="custom",
            description="A robot's recordings converted by `python -m data.demon.convert`.",
            train_files=("custom_train.h5", "custom_train_*.h5"),
            test_files=("custom_test.h5", "custom_test_*.h5"),
            globs=True,
        ),
    ]

    def __init__(
        self,
        *,
        strict: bool = False,
        max_bad_fraction: float = 0.05,
        verify_checksums: bool = True,
        flow_estimator: str = flow_lib.DEFAULT_ESTIMATOR,
        min_relative_baseline: float | None = None,
        depth_resampling: str | None = None,
        image_decoder: str | None = None,
        file_format: str | None = None,
        **kwargs,
    ):
        """Args: see the module docstring; `min_relative_baseline` None: per split
        (`pairs.MIN_RELATIVE_BASELINE`); `depth_resampling` None: the config's;
        `image_decoder` None: DeMoN's (`images.resolve_image_decoder`); `file_format` None:
        `data.FILE_FORMAT`. Other arguments go to TFDS."""
        if not 0.0 <= max_bad_fraction <= 1.0:
            raise ValueError(f"max_bad_fraction must be in [0, 1], got {max_bad_fraction}")
        flow_lib.check_estimator(flow_estimator)
        if depth_resampling is not None and depth_resampling not in pairs.DEPTH_RESAMPLING:
            raise ValueError(
                f"unknown depth_resampling {depth_resampling!r}; "
                f"valid: {sorted(pairs.DEPTH_RESAMPLING)}"
            )
        if min_relative_baseline is not None and not min_relative_baseline >= 0.0:
            raise ValueError(f"min_relative_baseline must be >= 0, got {min_relative_baseline}")
        self._strict = strict
        self._max_bad_fraction = max_bad_fraction
        self._verify_checksums = verify_checksums
        self._flow_estimator = flow_estimator
        self._min_relative_baseline = min_relative_baseline
        self._depth_resampling = depth_resampling
        self._image_decoder = images.resolve_image_decoder(image_decoder)
        super().__init__(file_format=file_format or data.FILE_FORMAT, **kwargs)

    def build_options(self, split: str) -> dict[str, Any]:
        """The options that shape the records of `split`, their order included (stored
        in the metadata: the protocol the records were built with)."""
        min_relative_baseline = self._min_relative_baseline
        if min_relative_baseline is None:
            min_relative_baseline = pairs.MIN_RELATIVE_BASELINE[split]
        return {
            "min_baseline": pairs.MIN_BASELINE,
            "min_relative_baseline": min_relative_baseline,
            "depth_resampling": self._depth_resampling or self.builder_config.depth_resampling,
            "image_decoder": self._image_decoder,
            "flow_estimator": self._flow_estimator,
            "order": ORDER,
        }

    def _info(self) -> tfds.core.DatasetInfo:
        return tfds.core.DatasetInfo(
            builder=self,
            description=__doc__,
            features=records.features(pairs.HEIGHT, pairs.WIDTH),
            homepage="https://github.com/lmb-freiburg/demon",
            metadata=tfds.core.MetadataDict(),
            # Records stay in the order `pairs.generate` yields them (DeMoN's), keyed by
            # their position; the id is a feature.
            disable_shuffling=True,
        )

    def source_files(self, manual_dir: Path) -> dict[str, list[Path]]:
        """Split -> the files of the split present in `manual_dir`, sorted; splits
        without any left out. (`data.prepare` compares them with a build's sources.)"""
        config: DemonConfig = self.builder_config
        found: dict[str, list[Path]] = {}
        for split, names in (("train", config.train_files), ("test", config.test_files)):
            if config.globs:
                paths = sorted({path for name in names for path in manual_dir.glob(name)})
            else:
                paths = [manual_dir / name for name in names if (manual_dir / name).is_file()]
            if paths:
                found[split] = paths
        return found

    def _split_files(self, manual_dir: Path) -> dict[str, list[Path]]:
        """Split -> files present in the manual directory (splits without files left out)."""
        config: DemonConfig = self.builder_config
        if config.name == "rgbd":
            for leaky in sorted(manual_dir.glob("rgbd_*_train.h5")):
                if not checksums.is_leaky_rgbd_file(leaky.name):
                    continue
                fixed = leaky.name.replace("rgbd_", "rgbd_bugfix_", 1)
                if not (manual_dir / fixed).exists():
                    raise ValueError(checksums.leaky_file_message(leaky))
                _LOGGER.warning("ignoring %s: %s", leaky, checksums.leaky_file_message(leaky))
        found = self.source_files(manual_dir)
        if not config.globs:
            for split, names in (("train", config.train_files), ("test", config.test_files)):
                if split not in found:
                    _LOGGER.warning(
                        "demon/%s: no %s files in %s; the %s split is left out",
                        config.name,
                        split,
                        manual_dir,
                        split,
                    )
                    continue
                missing = [name for name in names if not (manual_dir / name).is_file()]
                if missing:
                    raise MissingFilesError(
                        f"--manual_dir={manual_dir}: demon/{config.name} {split} split: missing "
                        f"{missing} ({MISSING_FILES_HINT})"
                    )
        if not found:
            expected = list(config.train_files) + list(config.test_files)
            raise MissingFilesError(
                f"--manual_dir={manual_dir}: demon/{config.name}: none of {expected} "
                f"({MISSING_FILES_HINT})"
            )
        return found

    def _split_generators(self, dl_manager: tfds.download.DownloadManager):
        split_files = self._split_files(Path(dl_manager.manual_dir))
        paths = [path for split_paths in split_files.values() for path in split_paths]
        for path in paths:
            if checksums.is_leaky_rgbd_file(path.name):
                raise ValueError(checksums.leaky_file_message(path))
        # Every file of every split, before any split is built: a broken test file must
        # not surface only after hours spent on the train split. Structure only (cheap);
        # the MD5 sums, which read every byte, come after.
        reader.check_files(paths)
        reader.check_image_decoder(self._image_decoder, paths)
        if self._verify_checksums:
            for path in paths:
                checksums.verify(path)
        self.info.metadata["sources"] = sources.fingerprints(split_files)
        return {
            split: self._generate_examples(split_paths, split)
            for split, split_paths in split_files.items()
        }

    def _generate_examples(self, paths: list[Path], split: str):
        report = pairs.BuildReport(split)
        options = self.build_options(split)
        generated = pairs.generate(
            paths,
            split,
            strict=self._strict,
            max_bad_fraction=self._max_bad_fraction,
            flow_estimator=options["flow_estimator"],
            min_relative_baseline=options["min_relative_baseline"],
            depth_resampling=options["depth_resampling"],
            image_decoder=options["image_decoder"],
            report=report,
        )
        for position, (_, example) in enumerate(generated):
            yield position, records.encode(example)
        print(report.format(), flush=True)
        self.info.metadata.setdefault("build_report", {})[split] = report.as_dict()
        self.info.metadata.setdefault("build_options", {})[split] = options
        self.info.metadata["flow_estimator_source"] = trained_flow.describe_flow(
            options["flow_estimator"]
        )
