"""DeMoN examples' ground truth at their files' resolution, read back by example id.

A record holds depth at 256x192; DeMoN evaluates against the depth of its file (640x480
for SUN3D and RGB-D) with the prediction upsampled by nearest neighbour. `FileTruth`
serves that ground truth to `gld.evaluation.evaluate` (it is a
`gld.evaluation.evaluate.Truth`): for the
id `"<file>/<group>/<i>-<j>"` (`reader.example_id`) it reads view i of the group from
`<manual_dir>/<file>`, the camera-z depth as `reader.read_view` gives it (0 where not
finite and positive), and divides it by the record's ||t||, as
`gld.contract.normalise_scale` scales the record's depth.

    with FileTruth("~/demon") as truth:
        trained_run.evaluate_workdir(workdir, source, ..., truth=truth)

`check` reads both views of every example and compares the pair's ||t|| in the file
with the record's, so a manual directory that holds other files than the records were
built from is refused, naming the examples, before anything is scored.

`for_split(builder, split, manual_dir)` opens the truth of a built split: in
`manual_dir` if given, else where the build recorded its files (`data.sources`), once
the files found there are those the split was built from (size and SHA-256 of their
ends, as `data.prepare` compares them).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from data import sources
from data.demon import reader
from gld import geometry

# Relative difference between the file's and the record's ||t|| beyond float32 rounding.
_BASELINE_TOLERANCE = 1e-5
# Examples named in one error message.
_NAMED_EXAMPLES = 10


def parse_example_id(example_id: str) -> tuple[str, str, tuple[int, int]]:
    """`"<file name>/<group>/<i>-<j>"` -> (file name, group, (i, j)), the inverse of
    `reader.example_id` (a file name or a top-level HDF5 group has no "/").

    Raises:
      ValueError when the id is not of that form.
    """
    parts = str(example_id).split("/")
    first, _, second = parts[-1].partition("-")
    if len(parts) != 3 or not (first.isdigit() and second.isdigit()) or not all(parts[:2]):
        raise ValueError(
            f"example id {example_id!r} is not '<file>/<group>/<i>-<j>' (a DeMoN record's id)"
        )
    return parts[0], parts[1], (int(first), int(second))


class FileTruth:
    """View 1's depth of DeMoN examples at the resolution of the files in a folder."""

    def __init__(self, manual_dir: str | Path):
        """Args: manual_dir: the folder of DeMoN's HDF5 files the records were built from.

        Raises:
          FileNotFoundError when it is not a directory.
        """
        self.manual_dir = Path(manual_dir).expanduser()
        if not self.manual_dir.is_dir():
            raise FileNotFoundError(f"DeMoN files folder {self.manual_dir} does not exist")
        self._files: dict[str, reader.DemonFile] = {}
        self._baselines: dict[str, float] = {}
        self._shapes: dict[str, tuple[int, int]] = {}
        self._checked: list[tuple[str, float]] | None = None

    def __enter__(self) -> FileTruth:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def close(self) -> None:
        for demon_file in self._files.values():
            demon_file.close()
        self._files = {}

    def _file(self, name: str) -> reader.DemonFile:
        if name not in self._files:
            # Only depth and cameras are read; the images' decoding is irrelevant here.
            self._files[name] = reader.DemonFile(self.manual_dir / name, image_decoder="opencv")
        return self._files[name]

    def _view(self, example_id: str, which: int) -> reader.View:
        file_name, group, pair = parse_example_id(example_id)
        return self._file(file_name).view(group, pair[which])

    def check(self, examples: Iterable[tuple[str, float]]) -> None:
        """Reads both views of every example and remembers its ||t|| and truth shape;
        the examples checked last are not read again.

        Args:
          examples: (id, ||t|| of its record) of each example to be scored
            (`gld.evaluation.stored_predictions.record_ids_and_baselines`).

        Raises:
          ValueError naming every example whose id is not a DeMoN id, whose file is
          missing or unreadable, whose views are damaged, or whose pair's ||t|| in the
          file differs from the record's.
        """
        examples = list(examples)
        if examples == self._checked:  # checked where it was opened, then by the scorer
            return
        problems = []
        self._baselines, self._shapes, self._checked = {}, {}, None
        for example_id, baseline in examples:
            try:
                view1, view2 = self._view(example_id, 0), self._view(example_id, 1)
            except (ValueError, FileNotFoundError) as error:  # DamagedDataError too
                problems.append(f"{example_id}: {error}")
                continue
            _, translation = geometry.relative_pose(
                view1.rotation, view1.translation, view2.rotation, view2.translation
            )
            # As the record stores it (float32) and the input pipeline measures it.
            file_baseline = float(np.linalg.norm(translation.astype(np.float32)))
            if not abs(file_baseline - baseline) <= _BASELINE_TOLERANCE * baseline:
                problems.append(
                    f"{example_id}: ||t|| is {file_baseline:.6g} in the file, "
                    f"{baseline:.6g} in the record"
                )
                continue
            self._baselines[example_id] = baseline
            self._shapes[example_id] = view1.depth.shape
        if problems:
            lines = [
                f"the ground truth at the files' resolution cannot be read from "
                f"{self.manual_dir} (it must hold the DeMoN files the records were built "
                f"from) for {len(problems)} example(s):",
                *problems[:_NAMED_EXAMPLES],
            ]
            if len(problems) > _NAMED_EXAMPLES:
                lines.append(f"... and {len(problems) - _NAMED_EXAMPLES} more")
            raise ValueError("\n  ".join(lines))
        self._checked = examples

    def shapes(self) -> dict[str, tuple[int, int]]:
        """id -> (height, width) of its truth, for every checked example."""
        return dict(self._shapes)

    def maps(self, ids: Sequence[str]) -> list[tuple[np.ndarray, np.ndarray]]:
        """(depth [h, w] float32, ||t|| = 1, 0 where invalid; valid [h, w] bool) of view 1
        of each id at its file's resolution. Call `check` first."""
        unchecked = [example_id for example_id in ids if example_id not in self._baselines]
        if unchecked:
            raise ValueError(f"ids {unchecked[:_NAMED_EXAMPLES]} were not checked (call check)")
        maps = []
        for example_id in ids:
            depth = self._view(example_id, 0).depth
            valid = geometry.valid_depth(depth)
            # As `gld.contract.normalise_scale` scales the record's depth.
            depth = np.asarray(depth, np.float64) / self._baselines[example_id]
            maps.append((np.where(valid, depth, 0.0).astype(np.float32), valid))
        return maps

    def summary(self) -> dict[str, Any]:
        """Where the truth came from, for metrics.json."""
        return {"truth_files": str(self.manual_dir)}


def for_split(builder: Any, split: str, manual_dir: str | Path | None = None) -> FileTruth:
    """The file truth of `split` of a built `demon/*` dataset: the files in `manual_dir`,
    or, without it, in the folder the build recorded them in (`metadata["sources"]`).

    Raises:
      FileNotFoundError: no folder given and none recorded, or the folder or one of
        the split's files is not there.
      ValueError: a file there is not the one the split was built from (content).
    """
    recorded = (builder.info.metadata or {}).get("sources", {}).get(split)
    if manual_dir is not None:
        folder = Path(manual_dir).expanduser()
    elif recorded:
        folder = Path(next(iter(recorded.values()))["path"]).parent
    else:
        raise FileNotFoundError(
            f"{builder.info.full_name} records no source files for its {split} split "
            "(built by an earlier gld)"
        )
    if not folder.is_dir():
        raise FileNotFoundError(f"DeMoN files folder {folder} does not exist")
    if recorded:
        missing = sorted(name for name in recorded if not (folder / name).is_file())
        if missing:
            raise FileNotFoundError(f"{', '.join(missing)} not in {folder}")
        current = sources.fingerprints({split: [folder / name for name in recorded]})
        changes = sources.changes({split: recorded}, current)
        if changes:
            raise ValueError(
                f"the files in {folder} are not those the {split} split was built from: "
                + "; ".join(changes)
            )
    return FileTruth(folder)
