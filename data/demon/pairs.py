"""DeMoN views -> gld records: resizing, relative pose, flow, and damage accounting.

`generate(paths, split)` walks every planned pair of every file, yields raw
examples in the `gld.records` format at 256x192 and skips damaged pairs, counting
them by reason in a `BuildReport`. It fails only when the bad share exceeds
`max_bad_fraction` (or at the first bad pair with `strict=True`), so a
multi-hour build never dies on one bad group.
"""

from __future__ import annotations

import collections
import dataclasses
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from data.demon import reader
from gld import flow as flow_lib
from gld import geometry

HEIGHT, WIDTH = 192, 256


def resize_depth(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resizes a depth map without mixing valid and invalid (or fore- and background) values.

    Every output pixel takes the value of one input pixel: the centre-aligned
    nearest sample (OpenCV's INTER_NEAREST_EXACT; DeMoN's reader also resizes depth
    with nearest), so measured depths are kept and no "flying pixels" appear at
    depth edges, as averaging would create. Where that sample is invalid but the
    output pixel covers valid input pixels, the valid one closest to the output
    pixel's centre is taken, so sparse readings (one range-sensor pixel per frame)
    survive downsampling.

    Args:
      depth: [h, w] float32, 0 (or non-finite / negative) where invalid.
      height, width: output size.

    Returns:
      [height, width] float32, 0 where invalid.
    """
    source_height, source_width = depth.shape
    valid = geometry.valid_depth(depth)
    depth = np.where(valid, depth, 0.0).astype(np.float32)
    if (source_height, source_width) == (height, width):
        return depth
    resized = cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST_EXACT)
    holes = resized <= 0
    if not holes.any():
        return resized
    # Output pixel containing each input pixel's centre, per axis.
    row_target = np.minimum(
        ((np.arange(source_height) + 0.5) * (height / source_height)), height - 1e-6
    )
    col_target = np.minimum(
        ((np.arange(source_width) + 0.5) * (width / source_width)), width - 1e-6
    )
    row_index, col_index = row_target.astype(np.int64), col_target.astype(np.int64)
    rows, cols = np.nonzero(valid & holes[row_index[:, None], col_index[None, :]])
    if rows.size == 0:
        return resized
    target = row_index[rows] * width + col_index[cols]
    distance = (row_target[rows] - row_index[rows] - 0.5) ** 2 + (
        col_target[cols] - col_index[cols] - 0.5
    ) ** 2
    order = np.lexsort((distance, target))
    first = order[np.unique(target[order], return_index=True)[1]]
    resized.reshape(-1)[target[first]] = depth[rows[first], cols[first]]
    return resized


def resize_view(view: reader.View, height: int = HEIGHT, width: int = WIDTH) -> reader.View:
    """Image with INTER_AREA, depth with `resize_depth`; normalised intrinsics are unchanged."""
    image = view.image
    if image.shape[:2] != (height, width):
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    return dataclasses.replace(view, image=image, depth=resize_depth(view.depth, height, width))


def make_example(
    view1: reader.View,
    view2: reader.View,
    example_id: str,
    *,
    flow_estimator: str = flow_lib.DEFAULT_ESTIMATOR,
    min_relative_baseline: float = 1e-4,
) -> dict[str, Any]:
    """Two resized views -> a raw example in the `gld.records` format.

    Args:
      view1, view2: views at the output resolution (see `resize_view`).
      example_id: the id stored with the record.
      flow_estimator: a `gld.flow.ESTIMATORS` name.
      min_relative_baseline: a pair whose baseline is below this fraction of
        view 1's median depth has no usable parallax and is refused.

    Returns:
      dict with images [H, W, 3] uint8, metric depths [H, W], normalised intrinsics,
      the unnormalised relative pose (X2 = R X1 + t), estimated and ground-truth flow.

    Raises:
      reader.DamagedDataError (`zero_translation`).
    """
    rotation, translation = geometry.relative_pose(
        view1.rotation, view1.translation, view2.rotation, view2.translation
    )
    baseline = float(np.linalg.norm(translation))
    median_depth = float(np.median(view1.depth[view1.depth > 0]))
    if not baseline > min_relative_baseline * median_depth:
        raise reader.DamagedDataError(
            "zero_translation",
            example_id,
            f"baseline {baseline:.3g} <= {min_relative_baseline} x median depth {median_depth:.3g}",
        )
    gt_flow, gt_flow_valid = geometry.ground_truth_flow(
        view1.depth, view2.depth, view1.intrinsics, view2.intrinsics, rotation, translation
    )
    return {
        "image1": view1.image,
        "image2": view2.image,
        "depth1": view1.depth,
        "depth2": view2.depth,
        "intrinsics1": view1.intrinsics.astype(np.float32),
        "intrinsics2": view2.intrinsics.astype(np.float32),
        "rotation": rotation.astype(np.float32),
        "translation": translation.astype(np.float32),
        "flow": flow_lib.estimate(view1.image, view2.image, method=flow_estimator),
        "gt_flow": gt_flow,
        "gt_flow_valid": gt_flow_valid,
        "id": example_id,
    }


@dataclasses.dataclass
class BuildReport:
    """Pairs written and skipped (by reason) per file of one split."""

    split: str
    written: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    skipped: dict[str, collections.Counter] = dataclasses.field(default_factory=dict)
    planned: int = 0
    first_errors: list[str] = dataclasses.field(default_factory=list)

    @property
    def num_written(self) -> int:
        return sum(self.written.values())

    @property
    def num_skipped(self) -> int:
        return sum(sum(counts.values()) for counts in self.skipped.values())

    def skip(self, file_name: str, error: reader.DamagedDataError) -> None:
        self.skipped.setdefault(file_name, collections.Counter())[error.reason] += 1
        if len(self.first_errors) < 20:
            self.first_errors.append(str(error))

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready summary (stored in the dataset's metadata)."""
        files = sorted(set(self.written) | set(self.skipped))
        return {
            "split": self.split,
            "pairs_planned": self.planned,
            "pairs_written": self.num_written,
            "pairs_skipped": self.num_skipped,
            "files": {
                name: {
                    "written": self.written.get(name, 0),
                    "skipped": dict(sorted(self.skipped.get(name, {}).items())),
                }
                for name in files
            },
            "first_errors": list(self.first_errors),
        }

    def format(self) -> str:
        """A human-readable table: pairs per file, skipped per reason."""
        lines = [f"DeMoN build report, split {self.split!r}:"]
        for name, counts in self.as_dict()["files"].items():
            skipped = ", ".join(f"{reason}: {n}" for reason, n in counts["skipped"].items())
            lines.append(
                f"  {name}: {counts['written']} pairs written, "
                f"{sum(counts['skipped'].values())} skipped" + (f" ({skipped})" if skipped else "")
            )
        lines.append(
            f"  total: {self.num_written} written, {self.num_skipped} skipped "
            f"of {self.planned} planned"
        )
        lines.extend(f"  e.g. {error}" for error in self.first_errors[:5])
        return "\n".join(lines)


def _planned_pairs(demon_file: reader.DemonFile, split: str) -> list[tuple[str, Any]]:
    """(group, pair) for every pair to build; (group, error) for a group without usable pairs."""
    planned = []
    for group in demon_file.groups():
        try:
            planned.extend((group, pair) for pair in demon_file.pairs(group, split))
        except reader.DamagedDataError as error:
            planned.append((group, error))
    return planned


def generate(
    paths: Sequence[str | Path],
    split: str,
    *,
    strict: bool = False,
    max_bad_fraction: float = 0.05,
    flow_estimator: str = flow_lib.DEFAULT_ESTIMATOR,
    min_relative_baseline: float = 1e-4,
    report: BuildReport | None = None,
    height: int = HEIGHT,
    width: int = WIDTH,
) -> Iterator[tuple[str, dict[str, Any]]]:
    """Yields (id, raw example) for every usable pair of the files, in file and group order.

    Args:
      paths: DeMoN HDF5 files of one split.
      split: "train" (all listed pairs per group) or "test" (the first pair per group).
      strict: raise at the first damaged pair instead of skipping it.
      max_bad_fraction: raise once more than this share of the planned pairs is damaged.
      flow_estimator, min_relative_baseline: see `make_example`.
      report: filled with written / skipped counts (a new one if None).
      height, width: output resolution.

    Raises:
      reader.DamagedDataError: in strict mode, the first damaged pair.
      ValueError: when the bad share exceeds `max_bad_fraction`.
    """
    if not 0.0 <= max_bad_fraction <= 1.0:
        raise ValueError(f"max_bad_fraction must be in [0, 1], got {max_bad_fraction}")
    report = report if report is not None else BuildReport(split)
    files = [reader.DemonFile(path) for path in paths]
    try:
        plans = [(demon_file, _planned_pairs(demon_file, split)) for demon_file in files]
        report.planned = sum(len(plan) for _, plan in plans)

        def skip(demon_file: reader.DemonFile, error: reader.DamagedDataError) -> None:
            if strict:
                raise error
            report.skip(demon_file.name, error)
            if report.num_skipped > max_bad_fraction * report.planned:
                raise ValueError(
                    f"{report.num_skipped} of {report.planned} planned pairs are damaged, more "
                    f"than max_bad_fraction={max_bad_fraction}; latest: {error}\n" + report.format()
                )

        for demon_file, plan in plans:
            report.written[demon_file.name] += 0  # list files without usable pairs too
            resized: dict[tuple[str, int], reader.View] = {}
            for group, pair in plan:
                if isinstance(pair, reader.DamagedDataError):
                    skip(demon_file, pair)
                    continue
                example_id = reader.example_id(demon_file.name, group, pair)
                try:
                    views = []
                    for index in pair:
                        if (group, index) not in resized:
                            if resized and next(iter(resized))[0] != group:
                                resized.clear()  # keep only the current group's views
                            view = demon_file.view(group, index)
                            resized[group, index] = resize_view(view, height, width)
                        views.append(resized[group, index])
                    example = make_example(
                        *views,
                        example_id,
                        flow_estimator=flow_estimator,
                        min_relative_baseline=min_relative_baseline,
                    )
                except reader.DamagedDataError as error:
                    if error.where != example_id:
                        error = reader.DamagedDataError(
                            error.reason, example_id, f"{error.where}: {error.detail}"
                        )
                    skip(demon_file, error)
                    continue
                report.written[demon_file.name] += 1
                yield example_id, example
    finally:
        for demon_file in files:
            demon_file.close()
