"""A recording's prediction folder (`recordings.predict_recording`, `python -m
experiments.predict`): the files the predictor writes there, one run per folder.

    depth/<frame1>__<frame2>.png or .npy, preview/<...>.png, ply/<...>.ply,
    pairs.csv, summary.json

A folder describes exactly one run. A run is written into a hidden staging folder inside
the output folder (`.predict-*.partial`) and moved into place once every pair is written,
summary.json last; a run that fails or is stopped leaves the folder as it was. A folder
that holds an earlier run's files (a finished run's, an unfinished one's pairs.csv and
depth files, or a killed run's staging folder) is refused unless `overwrite`; then those
files, and only those, are removed when the new run is complete, so a file the predictor
does not write (notes, the recording itself) stays. A path the run writes that holds
something the predictor did not write (another tool's pairs.csv) is refused even with
`overwrite`.

    with staged_run("out", overwrite=False) as run_dir:   # raises before anything is written
        ...write the run into run_dir...
"""

from __future__ import annotations

import collections
import contextlib
import csv
import json
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path

SUMMARY = "summary.json"
PAIRS_CSV = "pairs.csv"
PAIRS_HEADER = ["pair", "frame1", "frame2", "scale", "scale_source", "units", "depth"]
# The folders of per-pair files, with the suffixes the predictor writes there.
PAIR_FOLDERS = {"depth": (".png", ".npy"), "preview": (".png",), "ply": (".ply",)}
_STAGING_PREFIX, _STAGING_SUFFIX = ".predict-", ".partial"
# Keys every summary.json the predictor writes has.
_SUMMARY_KEYS = {"pairs_written", "pairs_skipped", "scale_source", "units", "depth_format"}


def _is_staging(path: Path) -> bool:
    name = path.name
    return path.is_dir() and name.startswith(_STAGING_PREFIX) and name.endswith(_STAGING_SUFFIX)


def _is_own_pairs_csv(path: Path) -> bool:
    try:
        with path.open(newline="") as stream:
            return next(csv.reader(stream), None) == PAIRS_HEADER
    except (OSError, UnicodeDecodeError, csv.Error):
        return False


def _is_own_summary(path: Path) -> bool:
    try:
        summary = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(summary, dict) and _SUMMARY_KEYS <= set(summary)


def earlier_run(out_dir: str | Path, *, exclude: Path | None = None) -> list[Path]:
    """The files of an earlier run in `out_dir` (its summary.json, pairs.csv, per-pair
    files, and the staging folders of killed runs; `exclude` is one to leave out), which
    a new run with `overwrite` replaces; [] when there are none."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        return []
    found = [path for path in sorted(out_dir.iterdir()) if _is_staging(path) and path != exclude]
    if (out_dir / SUMMARY).is_file() and _is_own_summary(out_dir / SUMMARY):
        found.append(out_dir / SUMMARY)
    if (out_dir / PAIRS_CSV).is_file() and _is_own_pairs_csv(out_dir / PAIRS_CSV):
        found.append(out_dir / PAIRS_CSV)
    for folder, suffixes in PAIR_FOLDERS.items():
        if (out_dir / folder).is_dir():
            found += sorted(
                path
                for path in (out_dir / folder).iterdir()
                if path.is_file() and path.suffix in suffixes and "__" in path.stem
            )
    return found


def _described(out_dir: Path, paths: Sequence[Path]) -> str:
    """An earlier run's files in a few words: "summary.json, pairs.csv, 19 in depth/"."""
    counts = collections.Counter(path.relative_to(out_dir).parts[0] for path in paths)
    words = []
    for name, count in counts.items():
        if name in PAIR_FOLDERS:
            words.append(f"{count} in {name}/")
        elif name.startswith(_STAGING_PREFIX):
            words.append(f"{name}, the staging folder of a run that was stopped")
        else:
            words.append(name)
    return ", ".join(words)


def check_output_dir(out_dir: str | Path, *, overwrite: bool = False) -> list[Path]:
    """Checks, before anything is written, that a run may write into `out_dir`.

    Returns:
      The earlier run's files that the run replaces (`earlier_run`; only with `overwrite`).

    Raises:
      FileExistsError: `out_dir` holds an earlier run and `overwrite` is False.
      ValueError: `out_dir` is not a folder, or a path the run writes holds something
        the predictor did not write (even with `overwrite`: that is not its to remove).
    """
    out_dir = Path(out_dir)
    if not out_dir.exists():
        return []
    if not out_dir.is_dir():
        raise ValueError(f"{out_dir} is not a folder")
    foreign = [
        path
        for path, own in [
            (out_dir / SUMMARY, _is_own_summary),
            (out_dir / PAIRS_CSV, _is_own_pairs_csv),
        ]
        if path.exists() and not (path.is_file() and own(path))
    ]
    foreign += [
        out_dir / folder
        for folder in PAIR_FOLDERS
        if (out_dir / folder).exists() and not (out_dir / folder).is_dir()
    ]
    if foreign:
        raise ValueError(
            f"{', '.join(map(str, foreign))}: not the predictor's, where the run would write "
            "(it is kept): choose another output folder"
        )
    earlier = earlier_run(out_dir)
    if earlier and not overwrite:
        raise FileExistsError(
            f"{out_dir} holds an earlier prediction ({_described(out_dir, earlier)}); pass "
            "--overwrite (overwrite=True) to replace its files (and only those), or choose "
            "another output folder"
        )
    return earlier


@contextlib.contextmanager
def staged_run(out_dir: str | Path, *, overwrite: bool = False) -> Iterator[Path]:
    """A staging folder to write one run into, moved into `out_dir` when the block ends
    without an error (module docstring); on an error it is removed, and so is `out_dir`
    when the run made it and it is empty.

    Raises:
      As `check_output_dir`, before anything is written.
    """
    out_dir = Path(out_dir)
    check_output_dir(out_dir, overwrite=overwrite)
    made_out_dir = not out_dir.exists()
    out_dir.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=_STAGING_PREFIX, suffix=_STAGING_SUFFIX, dir=out_dir))
    try:
        yield staging
        _move_into_place(staging, out_dir, overwrite=overwrite)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        if made_out_dir and out_dir.is_dir() and not any(out_dir.iterdir()):
            out_dir.rmdir()
        raise


def _move_into_place(staging: Path, out_dir: Path, *, overwrite: bool) -> None:
    """The staged run's files into `out_dir`, after the earlier run's files are removed;
    summary.json goes first and comes last, so no summary ever sits beside another run."""
    earlier = earlier_run(out_dir, exclude=staging)
    if earlier and not overwrite:  # another run finished into the folder meanwhile
        raise FileExistsError(f"{out_dir} got an earlier prediction's files while this one ran")
    for path in sorted(earlier, key=lambda path: path.name != SUMMARY):
        if path.is_dir():
            shutil.rmtree(path)
        else:
            path.unlink()
    for folder in PAIR_FOLDERS:
        if (out_dir / folder).is_dir() and not any((out_dir / folder).iterdir()):
            (out_dir / folder).rmdir()
    staged = [path for path in staging.rglob("*") if path.is_file()]
    for path in sorted(staged, key=lambda path: path == staging / SUMMARY):
        target = out_dir / path.relative_to(staging)
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(path, target)
    shutil.rmtree(staging)
