"""DeMoN views -> gld records: resizing, relative pose, flow, and damage accounting.

`generate(paths, split)` walks every planned pair of every file, yields raw
examples in the `gld.records` format at 256x192 and skips damaged pairs, counting
them by reason in a `BuildReport`. It fails only when the bad share exceeds
`max_bad_fraction` (or at the first bad pair with `strict=True`), so a
multi-hour build never dies on one bad group.

Which pairs are kept, and in which order, follows DeMoN's reader op: a pair is
skipped for its baseline only when ||t|| < 1e-6 (`MIN_BASELINE`), counted apart from
damage (`damage.FILTER_REASONS`); files come in the order given, each file's scene
groups reverse-sorted (`reader.demon_order`), a group's pairs as listed. gld's
relative threshold (baseline <= 1e-4 x median depth, no usable parallax) is a build
option applied by default to the training split only (`MIN_RELATIVE_BASELINE`), so the
test split holds every pair DeMoN evaluates; the report counts the small-baseline
pairs it keeps.
"""

from __future__ import annotations

import collections
import dataclasses
import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from data.demon import damage, images, reader
from gld import flow as flow_lib
from gld import geometry
from gld.runs import trained_flow

HEIGHT, WIDTH = 192, 256

# DeMoN skips a pair with ||t|| below this; `gld.contract.normalise_scale`
# refuses the same pairs (it divides depth by ||t||).
MIN_BASELINE = 1e-6
# Default per split of the relative-baseline threshold (a build option): a pair with
# baseline <= this x view 1's median depth is skipped as `small_baseline`. Off (0) for
# the test split, which must keep every pair DeMoN evaluates.
MIN_RELATIVE_BASELINE = {"train": 1e-4, "test": 0.0}
# The build report counts the kept pairs at or below this relative baseline.
SMALL_RELATIVE_BASELINE = 1e-4


def resize_depth_demon(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resizes a depth map as DeMoN's reader op does: OpenCV's plain INTER_NEAREST.

    Output pixel (y, x) takes input pixel (floor(y * h / height), floor(x * w / width))
    (top-left aligned), valid or not; no hole is filled, so a sparse reading
    survives only if it lies on a sampled pixel.

    Args:
      depth: [h, w] float32, 0 (or non-finite / negative) where invalid.
      height, width: output size.

    Returns:
      [height, width] float32, 0 where invalid.
    """
    depth = np.where(geometry.valid_depth(depth), depth, 0.0).astype(np.float32)
    if depth.shape == (height, width):
        return depth
    return cv2.resize(depth, (width, height), interpolation=cv2.INTER_NEAREST)


def resize_depth_centred(depth: np.ndarray, height: int, width: int) -> np.ndarray:
    """Resizes a depth map by centred nearest sampling, filling holes from covered pixels.

    gld's convention (DeMoN's is `resize_depth_demon`). Every output pixel takes
    the value of one input pixel: the centre-aligned nearest sample (OpenCV's
    INTER_NEAREST_EXACT), so measured depths are kept and no "flying pixels" appear at
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


# Depth resampling conventions by name (a build option; see data/demon/README.md).
DEPTH_RESAMPLING = {"demon": resize_depth_demon, "centred": resize_depth_centred}
DEFAULT_DEPTH_RESAMPLING = "demon"


def resize_view(
    view: reader.View,
    height: int = HEIGHT,
    width: int = WIDTH,
    depth_resampling: str = DEFAULT_DEPTH_RESAMPLING,
) -> reader.View:
    """Image with INTER_AREA, depth by a `DEPTH_RESAMPLING` convention.

    Normalised intrinsics are unchanged. With `demon`, ray-length depth is resampled
    as ray length and converted to camera z at the output resolution, in DeMoN's order.
    """
    if depth_resampling not in DEPTH_RESAMPLING:
        raise ValueError(
            f"unknown depth resampling {depth_resampling!r}; valid: {sorted(DEPTH_RESAMPLING)}"
        )
    image = view.image
    if image.shape[:2] != (height, width):
        image = cv2.resize(image, (width, height), interpolation=cv2.INTER_AREA)
    resize_depth = DEPTH_RESAMPLING[depth_resampling]
    depth = view.depth
    if depth_resampling == "demon" and view.depth_metric == "ray_length":
        ray_length = depth * reader.ray_norms(view.intrinsics, *depth.shape)
        depth = reader.ray_length_to_camera_z(
            resize_depth(ray_length, height, width), view.intrinsics
        )
    else:
        depth = resize_depth(depth, height, width)
    return dataclasses.replace(view, image=image, depth=depth)


def relative_baseline(view1: reader.View, view2: reader.View, example_id: str) -> float:
    """The pair's baseline ||t|| over view 1's median valid depth (NaN without valid depth).

    Raises:
      damage.DamagedDataError (`zero_translation`) when ||t|| < MIN_BASELINE, as DeMoN skips.
    """
    _, translation = geometry.relative_pose(
        view1.rotation, view1.translation, view2.rotation, view2.translation
    )
    baseline = float(np.linalg.norm(translation))
    if not baseline >= MIN_BASELINE:
        raise damage.DamagedDataError(
            "zero_translation", example_id, f"baseline {baseline:.3g} < {MIN_BASELINE}"
        )
    valid_depth = view1.depth[view1.depth > 0]
    # No valid depth left (a sparse map after resampling): kept, as DeMoN keeps it.
    return baseline / float(np.median(valid_depth)) if valid_depth.size else float("nan")


def make_example(
    view1: reader.View,
    view2: reader.View,
    example_id: str,
    *,
    flow_estimator: str = flow_lib.DEFAULT_ESTIMATOR,
) -> dict[str, Any]:
    """Two resized views -> a raw example in the `gld.records` format.

    Args:
      view1, view2: views at the output resolution (see `resize_view`).
      example_id: the id stored with the record.
      flow_estimator: a `gld.flow.check_estimator` name.

    Returns:
      dict with images [H, W, 3] uint8, metric depths [H, W], normalised intrinsics,
      the unnormalised relative pose (X2 = R X1 + t), estimated and ground-truth flow.
    """
    rotation, translation = geometry.relative_pose(
        view1.rotation, view1.translation, view2.rotation, view2.translation
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
        "flow": trained_flow.estimate_flow(view1.image, view2.image, method=flow_estimator),
        "gt_flow": gt_flow,
        "gt_flow_valid": gt_flow_valid,
        "id": example_id,
    }


@dataclasses.dataclass
class BuildReport:
    """Pairs written and skipped (by reason) per file of one split.

    Skipped pairs are damage, or filtered (`damage.FILTER_REASONS`: no baseline, as
    DeMoN skips them, or below `min_relative_baseline`), which are counted apart.
    `small_baseline` counts, per file, the written pairs whose baseline is at most
    SMALL_RELATIVE_BASELINE x view 1's median depth (kept, as DeMoN keeps them);
    `no_valid_depth` the written pairs whose view 1 has no valid depth left at the
    output resolution (sparse readings that DeMoN's resampling does not sample).
    """

    split: str
    written: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    skipped: dict[str, collections.Counter] = dataclasses.field(default_factory=dict)
    small_baseline: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    no_valid_depth: collections.Counter = dataclasses.field(default_factory=collections.Counter)
    planned: int = 0
    first_errors: list[str] = dataclasses.field(default_factory=list)

    @property
    def num_written(self) -> int:
        return sum(self.written.values())

    @property
    def num_skipped(self) -> int:
        return sum(sum(counts.values()) for counts in self.skipped.values())

    @property
    def num_damaged(self) -> int:
        """Skipped pairs other than the filtered ones (`damage.FILTER_REASONS`)."""
        return self.num_skipped - sum(self.filtered().values())

    def filtered(self) -> dict[str, int]:
        """Reason -> pairs skipped for it over all files, for each of
        `damage.FILTER_REASONS` (0 included)."""
        return {
            reason: sum(counts.get(reason, 0) for counts in self.skipped.values())
            for reason in damage.FILTER_REASONS
        }

    def skip(self, file_name: str, error: damage.DamagedDataError) -> None:
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
            "pairs_damaged": self.num_damaged,
            "pairs_filtered": self.filtered(),
            "small_baseline_written": sum(self.small_baseline.values()),
            "small_relative_baseline": SMALL_RELATIVE_BASELINE,
            "no_valid_depth_written": sum(self.no_valid_depth.values()),
            "files": {
                name: {
                    "written": self.written.get(name, 0),
                    "skipped": dict(sorted(self.skipped.get(name, {}).items())),
                    "small_baseline_written": self.small_baseline.get(name, 0),
                    "no_valid_depth_written": self.no_valid_depth.get(name, 0),
                }
                for name in files
            },
            "first_errors": list(self.first_errors),
        }

    def format(self) -> str:
        """A human-readable table: pairs per file, skipped per reason, small baselines kept."""
        lines = [f"DeMoN build report, split {self.split!r}:"]
        for name, counts in self.as_dict()["files"].items():
            skipped = ", ".join(f"{reason}: {n}" for reason, n in counts["skipped"].items())
            lines.append(
                f"  {name}: {counts['written']} pairs written "
                f"({counts['small_baseline_written']} with a small baseline), "
                f"{sum(counts['skipped'].values())} skipped" + (f" ({skipped})" if skipped else "")
            )
        filtered = self.filtered()
        lines.append(
            f"  total: {self.num_written} written, {self.num_skipped} skipped "
            f"({self.num_damaged} damaged; not damage: {filtered['zero_translation']} without "
            f"a baseline, ||t|| < {MIN_BASELINE:g}, skipped as DeMoN skips them, "
            f"{filtered['small_baseline']} below min_relative_baseline) of {self.planned} "
            f"planned; {sum(self.small_baseline.values())} written pairs have a small "
            f"baseline (<= {SMALL_RELATIVE_BASELINE:g} x median depth)"
        )
        no_valid_depth = sum(self.no_valid_depth.values())
        if no_valid_depth:
            lines.append(
                f"  {no_valid_depth} written pairs have no valid depth in view 1 after "
                f"resampling (sparse readings off DeMoN's sampled pixels; "
                f"depth_resampling=centred keeps them)"
            )
        lines.extend(f"  e.g. {error}" for error in self.first_errors[:5])
        return "\n".join(lines)


def _planned_pairs(demon_file: reader.DemonFile, split: str) -> list[tuple[str, Any]]:
    """(group, pair) for every pair to build, in DeMoN's order (`reader.demon_order`);
    (group, error) for a group without usable pairs."""
    planned = []
    for group in reader.demon_order(demon_file.groups()):
        try:
            planned.extend((group, pair) for pair in demon_file.pairs(group, split))
        except damage.DamagedDataError as error:
            planned.append((group, error))
    return planned


def generate(
    paths: Sequence[str | Path],
    split: str,
    *,
    strict: bool = False,
    max_bad_fraction: float = 0.05,
    flow_estimator: str = flow_lib.DEFAULT_ESTIMATOR,
    min_relative_baseline: float | None = None,
    depth_resampling: str = DEFAULT_DEPTH_RESAMPLING,
    image_decoder: str | None = None,
    report: BuildReport | None = None,
    height: int = HEIGHT,
    width: int = WIDTH,
) -> Iterator[tuple[str, dict[str, Any]]]:
    """Yields (id, raw example) for every usable pair of the files, in DeMoN's order: the
    files as given, each file's groups reverse-sorted, each group's pairs as listed.

    Args:
      paths: DeMoN HDF5 files of one split.
      split: "train" (all listed pairs per group) or "test" (the first pair per group).
      strict: raise at the first damaged pair instead of skipping it.
      max_bad_fraction: raise once more than this share of the planned pairs is damaged
        (filtered pairs, `damage.FILTER_REASONS`, are not damaged).
      flow_estimator: see `make_example`.
      min_relative_baseline: skip a pair (`small_baseline`) whose baseline is at most
        this x view 1's median depth; None: the split's `MIN_RELATIVE_BASELINE`.
      depth_resampling: a `DEPTH_RESAMPLING` name (see `resize_view`).
      image_decoder: a `images.IMAGE_DECODERS` name, None for DeMoN's
        (`images.resolve_image_decoder`).
      report: filled with written / skipped counts (a new one if None).
      height, width: output resolution.

    Raises:
      damage.DamagedDataError: in strict mode, the first damaged pair.
      images.MissingDecoderError: DeMoN's decoding of a lossy image without `webp`.
      ValueError: when the bad share exceeds `max_bad_fraction`.
    """
    if not 0.0 <= max_bad_fraction <= 1.0:
        raise ValueError(f"max_bad_fraction must be in [0, 1], got {max_bad_fraction}")
    if min_relative_baseline is None:
        min_relative_baseline = MIN_RELATIVE_BASELINE[split]
    image_decoder = images.resolve_image_decoder(image_decoder)
    report = report if report is not None else BuildReport(split)
    files = [reader.DemonFile(path, image_decoder) for path in paths]
    try:
        reader.check_image_decoder(image_decoder, paths)
        plans = [(demon_file, _planned_pairs(demon_file, split)) for demon_file in files]
        report.planned = sum(len(plan) for _, plan in plans)

        def skip(demon_file: reader.DemonFile, error: damage.DamagedDataError) -> None:
            if strict and error.reason not in damage.FILTER_REASONS:
                raise error
            report.skip(demon_file.name, error)
            if report.num_damaged > max_bad_fraction * report.planned:
                raise ValueError(
                    f"{report.num_damaged} of {report.planned} planned pairs are damaged, more "
                    f"than max_bad_fraction={max_bad_fraction}; latest: {error}\n" + report.format()
                )

        for demon_file, plan in plans:
            report.written[demon_file.name] += 0  # list files without usable pairs too
            resized: dict[tuple[str, int], reader.View] = {}
            for group, pair in plan:
                if isinstance(pair, damage.DamagedDataError):
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
                            resized[group, index] = resize_view(
                                view, height, width, depth_resampling
                            )
                        views.append(resized[group, index])
                    relative = relative_baseline(*views, example_id)
                    if relative <= min_relative_baseline:
                        raise damage.DamagedDataError(
                            "small_baseline",
                            example_id,
                            f"baseline {relative:.3g} x median depth <= min_relative_baseline="
                            f"{min_relative_baseline:g}",
                        )
                    example = make_example(*views, example_id, flow_estimator=flow_estimator)
                except damage.DamagedDataError as error:
                    if error.where != example_id:
                        error = damage.DamagedDataError(
                            error.reason, example_id, f"{error.where}: {error.detail}"
                        )
                    skip(demon_file, error)
                    continue
                report.written[demon_file.name] += 1
                report.small_baseline[demon_file.name] += relative <= SMALL_RELATIVE_BASELINE
                report.no_valid_depth[demon_file.name] += math.isnan(relative)
                yield example_id, example
    finally:
        for demon_file in files:
            demon_file.close()
