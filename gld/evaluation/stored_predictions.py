"""Depth maps written by other systems, read so that gld scores them under its protocol.

A folder holds one file per example, named by the example's id with every "/" replaced
by "__" (`file_stem`; id "sun3d_test.h5/0003/0-1" -> "sun3d_test.h5__0003__0-1.npy"):

* `<stem>.npy`: a 2-D floating-point array of depth;
* `<stem>.png`: a single-channel 16-bit PNG whose values times `png_depth_scale` are
  depth (0.001, the default, reads millimetres as metres).

A value that is not positive (a PNG's 0) means "no prediction": the metrics exclude such
pixels and count them (`gld.evaluation.metrics.depth_metrics`). NaN or inf in a file is refused.
Depth is in the protocol's scale ("normalised": the pair's translation has norm 1, as
gld's models and DeMoN's network predict) or in the dataset's stored units ("raw", e.g.
metres), then divided by the pair's ||t|| as the ground truth is. A map at another
resolution is resized to the evaluation resolution by centre-aligned nearest neighbour
(`gld.evaluation.metrics.resize_nearest`, DeMoN's rule); it must have the same aspect ratio. The
evaluation resolution is the records', or, when the ground truth is read at the source
files' resolution (`gld.evaluation.evaluate.Truth`), each example's truth's (`check(shapes=...)`),
so that a map is resized once, straight to the pixels it is scored on.

    predictions = StoredPredictions("out/other_system", depth_scale="raw")
    predictions.check(record_ids_and_baselines(source), height=192, width=256)
    evaluation.evaluate_predictor(predictions.predict, source)

`check` reads every file and raises one error naming every missing, ambiguous,
misshapen or non-finite file, so nothing is scored or written from a bad folder. A file
named by no example scored (a stray file, one in another format, or the rest of the
split when only its first examples are scored) is left out with a warning naming it,
and the protocol note and summary record it.
"""

from __future__ import annotations

import collections
import warnings
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from gld.evaluation import metrics

DEPTH_SCALES = ("normalised", "raw")
DEFAULT_DEPTH_SCALE = "normalised"
SUFFIXES = (".npy", ".png")
DEFAULT_PNG_DEPTH_SCALE = 0.001
# Aspect ratios further apart than this are a different crop, not a different resolution.
_ASPECT_TOLERANCE = 0.01
# Files named in one error message, per kind of problem.
_NAMED_FILES = 10


def file_stem(example_id: str) -> str:
    """The file name (without suffix) of an example's prediction: "/" -> "__"."""
    return str(example_id).replace("/", "__")


def record_ids_and_baselines(source: Sequence[Any]) -> list[tuple[str, float]]:
    """(id, ||t||) of every record of a source, ||t|| as the input pipeline computes it
    from the stored (raw) translation."""
    entries = []
    for index in range(len(source)):
        record = source[index]
        example_id = record["id"]
        example_id = example_id.decode() if isinstance(example_id, bytes) else str(example_id)
        translation = np.asarray(record["translation"], np.float32)
        entries.append((example_id, float(np.linalg.norm(translation))))
    return entries


def load_depth(path: str | Path, png_depth_scale: float = DEFAULT_PNG_DEPTH_SCALE) -> np.ndarray:
    """One stored prediction -> [h, w] float32 depth.

    Raises:
      ValueError naming the file: unreadable, not 2-D, not floating point (.npy) or not
        16-bit single-channel (.png), NaN or inf values.
    """
    path = Path(path)
    if path.suffix == ".npy":
        try:
            array = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as error:
            raise ValueError(f"{path}: not a readable .npy array ({error})") from None
        if not np.issubdtype(array.dtype, np.floating):
            raise ValueError(f"{path}: dtype {array.dtype}, expected floating-point depth")
        depth = array.astype(np.float32)
    elif path.suffix == ".png":
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise ValueError(f"{path}: not a readable PNG")
        if image.dtype != np.uint16 or image.ndim != 2:
            channels = 1 if image.ndim == 2 else image.shape[-1]
            raise ValueError(
                f"{path}: {image.dtype} with {channels} channel(s), expected a 16-bit "
                f"single-channel PNG"
            )
        depth = (image.astype(np.float64) * png_depth_scale).astype(np.float32)
    else:
        raise ValueError(f"{path}: unknown suffix, expected one of {SUFFIXES}")
    if depth.ndim != 2 or depth.size == 0:
        raise ValueError(f"{path}: shape {depth.shape}, expected a 2-D [H, W] depth map")
    non_finite = int(np.size(depth) - np.count_nonzero(np.isfinite(depth)))
    if non_finite:
        raise ValueError(f"{path}: {non_finite} NaN or inf value(s)")
    return depth


def _same_aspect(shape: tuple[int, int], height: int, width: int) -> bool:
    return abs((shape[1] / shape[0]) / (width / height) - 1.0) <= _ASPECT_TOLERANCE


def _listed(kind: str, items: list[str]) -> str:
    shown = ", ".join(items[:_NAMED_FILES])
    more = f" and {len(items) - _NAMED_FILES} more" if len(items) > _NAMED_FILES else ""
    return f"{len(items)} {kind}: {shown}{more}"


class StoredPredictions:
    """A folder of depth maps, one per example id, as a host-side predictor."""

    def __init__(
        self,
        folder: str | Path,
        *,
        depth_scale: str = DEFAULT_DEPTH_SCALE,
        png_depth_scale: float = DEFAULT_PNG_DEPTH_SCALE,
    ):
        """Args:
          folder: the files (see the module docstring for their names and formats).
          depth_scale: "normalised" (||t|| = 1) or "raw" (the dataset's units).
          png_depth_scale: depth per unit of a 16-bit PNG value.

        Raises:
          FileNotFoundError when `folder` is not a directory; ValueError for bad options.
        """
        self.folder = Path(folder).expanduser()
        if not self.folder.is_dir():
            raise FileNotFoundError(f"predictions folder {self.folder} does not exist")
        if depth_scale not in DEPTH_SCALES:
            raise ValueError(f"unknown depth_scale {depth_scale!r}; valid: {DEPTH_SCALES}")
        if not (np.isfinite(png_depth_scale) and png_depth_scale > 0):
            raise ValueError(f"png_depth_scale must be positive, got {png_depth_scale}")
        self.depth_scale = depth_scale
        self.png_depth_scale = png_depth_scale
        self._baselines: dict[str, float] = {}
        # (file shape, evaluation shape) -> examples.
        self._resolutions: collections.Counter[tuple[tuple[int, int], tuple[int, int]]] = (
            collections.Counter()
        )
        self._suffixes: set[str] = set()
        self._shapes: dict[str, tuple[int, int]] = {}
        self._unscored: list[str] = []

    def path(self, example_id: str) -> Path | None:
        """The example's file, None when there is none.

        Raises:
          ValueError when both a .npy and a .png file exist for it.
        """
        candidates = [self.folder / f"{file_stem(example_id)}{suffix}" for suffix in SUFFIXES]
        found = [path for path in candidates if path.is_file()]
        if len(found) > 1:
            raise ValueError(f"both {found[0].name} and {found[1].name} exist")
        return found[0] if found else None

    def check(
        self,
        examples: Iterable[tuple[str, float]],
        *,
        height: int,
        width: int,
        shapes: Mapping[str, tuple[int, int]] | None = None,
    ) -> None:
        """Reads the file of every example and remembers its pair's ||t||.

        Args:
          examples: (id, ||t||) of each example to be scored (`record_ids_and_baselines`).
          height, width: the evaluation resolution (the records').
          shapes: id -> (height, width) of its ground truth where that is scored at
            another resolution (`gld.evaluation.evaluate.Truth.shapes`); `predict` then gives each
            map at its example's.

        Raises:
          FileNotFoundError naming the missing files, ValueError naming the others
          (ambiguous, unreadable, misshapen, non-finite), each listing every problem;
          ValueError when two ids map to one file name.

        Warns:
          UserWarning naming the files of the folder that no example names (not scored).
        """
        missing, problems, stems = [], [], {}
        self._baselines, self._resolutions, self._suffixes = {}, collections.Counter(), set()
        self._shapes, self._unscored = {}, []
        for example_id, baseline in examples:
            stem = file_stem(example_id)
            if stems.setdefault(stem, example_id) != example_id:
                raise ValueError(
                    f"ids {stems[stem]!r} and {example_id!r} share the file name {stem!r}"
                )
            self._baselines[example_id] = baseline
            try:
                path = self.path(example_id)
                if path is None:
                    missing.append(stem)
                    continue
                shape = load_depth(path, self.png_depth_scale).shape
            except ValueError as error:
                problems.append(str(error))
                continue
            target = tuple((shapes or {}).get(example_id, (height, width)))
            if not _same_aspect(shape, *target):
                problems.append(
                    f"{path}: shape {shape}, expected the aspect ratio of the evaluation "
                    f"resolution {list(target)}"
                )
                continue
            self._shapes[example_id] = target
            self._resolutions[shape, target] += 1
            self._suffixes.add(path.suffix)
        if missing or problems:
            lines = [f"predictions in {self.folder} cannot be scored:"]
            if missing:
                present = sorted(p.name for p in self.folder.iterdir() if p.suffix in SUFFIXES)
                lines.append(_listed("example(s) without a <name>.npy or <name>.png", missing))
                lines.append(_listed("prediction file(s) in the folder", present))
                lines.append('a file is named by its example id with "/" replaced by "__"')
            lines += problems[:_NAMED_FILES]
            if len(problems) > _NAMED_FILES:
                lines.append(f"... and {len(problems) - _NAMED_FILES} more bad file(s)")
            error_type = FileNotFoundError if missing else ValueError
            raise error_type("\n  ".join(lines))
        # Not an error: scoring the first examples of a split's folder is allowed, and a
        # file no example names changes no score; but it may be a misnamed prediction.
        scored = {f"{stem}{suffix}" for stem in stems for suffix in SUFFIXES}
        self._unscored = sorted(p.name for p in self.folder.iterdir() if p.name not in scored)
        if self._unscored:
            warnings.warn(
                f"predictions in {self.folder}: {self._unscored_note()} (a file is named by "
                'its example id with "/" replaced by "__")',
                UserWarning,
                stacklevel=2,
            )

    def _unscored_note(self) -> str:
        return _listed("file(s) named by no example scored here, left out", self._unscored)

    def predict(self, batch: Mapping[str, Any]) -> dict[str, Any]:
        """{'depth': [B, H, W] float32} for the batch's ids, at the evaluation resolution
        `check` was given, in the protocol's scale (||t|| = 1); a list of [h, w] maps
        when the examples' resolutions differ. Call `check` first."""
        ids = [str(example_id) for example_id in batch["id"]]
        unchecked = [example_id for example_id in ids if example_id not in self._baselines]
        if unchecked:
            raise ValueError(f"ids {unchecked[:_NAMED_FILES]} were not checked (call check)")
        maps = []
        for example_id in ids:
            depth = metrics.resize_nearest(
                load_depth(self.path(example_id), self.png_depth_scale), *self._shapes[example_id]
            )
            if self.depth_scale == "raw":
                # As `contract.normalise_scale` scales the ground truth.
                depth = np.asarray(depth, np.float64) / self._baselines[example_id]
            maps.append(np.asarray(depth, np.float32))
        if len({depth.shape for depth in maps}) > 1:
            return {"depth": maps}
        return {"depth": np.stack(maps)}

    def protocol_note(self) -> str:
        """What the protocol stamp adds for these predictions (after `check`)."""
        scale = (
            "normalised depth (||t|| = 1)"
            if self.depth_scale == "normalised"
            else "raw depth divided by each pair's ||t||"
        )
        if ".png" in self._suffixes:
            scale += f", 16-bit PNG values x {self.png_depth_scale:g}"
        resolutions = []
        for (shape, (height, width)), count in sorted(self._resolutions.items()):
            text = f"{count} at {shape[1]}x{shape[0]}"
            if shape != (height, width):
                text += f" resized to {width}x{height} by centre-aligned nearest neighbour"
            resolutions.append(text)
        note = f"stored predictions from {self.folder} ({scale}): " + ", ".join(resolutions)
        return note + (f"; {self._unscored_note()}" if self._unscored else "")

    def summary(self) -> dict[str, Any]:
        """The fields metrics.json records about these predictions (after `check`)."""
        by_file: collections.Counter[str] = collections.Counter()
        for ((height, width), _), count in self._resolutions.items():
            by_file[f"{width}x{height}"] += count
        return {
            "predictions": str(self.folder),
            "predictions_depth_scale": self.depth_scale,
            "png_depth_scale": self.png_depth_scale,
            "prediction_resolutions": dict(by_file),
            "predictions_unscored_files": list(self._unscored),
        }
