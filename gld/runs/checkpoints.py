"""A run's verified orbax checkpoints: the TrainState ("state") and the grain iterator
("data").

    <workdir>/checkpoints/<step>/checksums.json   SHA-256 and size of every file of a step
    <workdir>/corrupt_checkpoints/<step>-<time>/  damaged checkpoints a resume moved aside

Checkpoints are verified. `save_checkpoint` waits for orbax to finish writing a step and
records the SHA-256 and size of each of its files; `restore_checkpoint` (and with it
`load_trained` and resuming) checks them before restoring. A damaged checkpoint (a file
changed, truncated or missing, or one orbax fails to restore) is skipped, naming the
file, and the newest intact one is used; if none is intact, `CorruptCheckpointError`
lists every step's fault and nothing is deleted. A resume moves the damaged newer steps
to `corrupt_checkpoints/` (kept, never deleted) so that it can save those steps again;
`load_trained` moves nothing. Checkpoints written before checksums existed are restored
unverified, with a `CheckpointWarning`. Hashing needs the files on a local or mounted
file system, and makes each save wait until orbax has written it. A save that finds the
disk full removes what it wrote and raises `gld.files.DiskFullError` in one line: the
checkpoints saved before stay as they were.
"""

from __future__ import annotations

import contextlib
import datetime
import functools
import hashlib
import json
import logging
import os
import shutil
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import NamedTuple

import jax
import orbax.checkpoint as ocp

from gld.arguments import MissingInputError, RunStoppedError
from gld.files import DiskFullError, no_space_error, write_atomically
from gld.runs.state import TrainState

CHECKSUMS_FILE = "checksums.json"
CHECKPOINTS_DIR = "checkpoints"
CORRUPT_CHECKPOINTS_DIR = "corrupt_checkpoints"


def last_checkpointed_step(workdir: str | Path) -> int:
    """The newest checkpoint's step of a run's workdir (0 without one). Orbax names a
    step's directory by its number once the step is written, so no manager is needed."""
    steps = (
        int(path.name)
        for path in (Path(workdir) / CHECKPOINTS_DIR).glob("*")
        if path.name.isdigit()
    )
    return max(steps, default=0)


class CorruptCheckpointError(RunStoppedError, ValueError):
    """A checkpoint's files do not match what was saved, or no checkpoint is intact."""


class CheckpointWarning(UserWarning):
    """A checkpoint was skipped, or restored without checksums to verify it."""


def checkpoint_warning(message: str) -> None:
    """Warns with a `CheckpointWarning` (the default `print_fn` of the restores)."""
    warnings.warn(message, CheckpointWarning, stacklevel=3)


@functools.cache
def save_arrays_from_one_replica() -> None:
    """Has orbax write each jax.Array from one replica, sliced by no jax op.

    On CPU orbax's default handler saves a replicated array in parallel over its
    replicas: each replica writes a slice, cut by an eager `jax.lax.slice_in_dim`, which
    compiles one program per shape and device. A run's state is replicated over the
    devices of one host, whose memory every replica shares: there is nothing to
    parallelise, and a model's first save compiled ~2 programs a leaf (DispNet's 64,
    2.6 s of compiles in a 2-step run; the slices took 31 s of the tiny suite's 102 s of
    saves). The arrays saved are the same, their chunks laid out otherwise; the handler
    is orbax's default but for that one option (registered once a process)."""
    from orbax.checkpoint._src.metadata import array_metadata_store

    handler = ocp.type_handlers.ArrayHandler(
        array_metadata_store=array_metadata_store.Store(), use_replica_parallel=False
    )
    # Orbax warns that the handler overrides its default, which is the point.
    logger = logging.getLogger("absl")
    logger.addFilter(quiet := lambda record: "overriding" not in record.getMessage())
    try:
        ocp.type_handlers.register_type_handler(jax.Array, handler, override=True)
    finally:
        logger.removeFilter(quiet)


def checkpoint_manager(
    workdir: str | Path, *, keep: int = 2, every: int = 1
) -> ocp.CheckpointManager:
    """The run's orbax manager: items "state" (TrainState) and "data" (grain iterator);
    arrays written from one replica (`save_arrays_from_one_replica`)."""
    import grain

    save_arrays_from_one_replica()
    return ocp.CheckpointManager(
        Path(workdir).absolute() / CHECKPOINTS_DIR,
        item_handlers={
            "state": ocp.StandardCheckpointHandler(),
            "data": grain.checkpoint.CheckpointHandler(),
        },
        options=ocp.CheckpointManagerOptions(
            max_to_keep=keep, save_interval_steps=every, create=True
        ),
    )


@contextlib.contextmanager
def saving_manager(workdir: str | Path, *, keep: int) -> Iterator[ocp.CheckpointManager]:
    """`checkpoint_manager` for a trainer that saves: on exit its pending saves finish,
    then it closes. When the trainer stops on an error, that error is the one raised:
    what orbax says while closing after it (about a save the error cut short, whose files
    `save_checkpoint` removed) cannot replace it."""
    manager = checkpoint_manager(workdir, keep=keep)
    try:
        yield manager
    except BaseException:
        with contextlib.suppress(Exception):
            _close(manager)
        raise
    _close(manager)


def _close(manager: ocp.CheckpointManager) -> None:
    manager.wait_until_finished()
    manager.close()


def step_directory(manager: ocp.CheckpointManager, step: int) -> Path:
    """Where orbax keeps checkpoint `step`."""
    return Path(str(manager.directory)) / str(step)


def _hash_file(path: Path) -> str:
    with path.open("rb") as stream:
        return hashlib.file_digest(stream, "sha256").hexdigest()


def _checkpoint_files(step_dir: Path) -> list[Path]:
    return sorted(
        path for path in step_dir.rglob("*") if path.is_file() and path.name != CHECKSUMS_FILE
    )


def record_checksums(step_dir: str | Path) -> None:
    """Writes `<step_dir>/checksums.json`: the SHA-256 and size of every file under it."""
    step_dir = Path(step_dir)
    files = {
        path.relative_to(step_dir).as_posix(): {
            "sha256": _hash_file(path),
            "bytes": path.stat().st_size,
        }
        for path in _checkpoint_files(step_dir)
    }
    payload = {"algorithm": "sha256", "files": files}
    write_atomically(step_dir / CHECKSUMS_FILE, json.dumps(payload, indent=1, sort_keys=True))


def verify_checksums(step_dir: str | Path) -> bool:
    """Checks a checkpoint's files against its `checksums.json`.

    Returns:
      True when every recorded file is there with its size and SHA-256; False when the
      checkpoint has no checksums (written by an earlier gld version).

    Raises:
      CorruptCheckpointError: a file is missing, has another size or another hash, or
        checksums.json is unreadable (the file is named).
    """
    step_dir = Path(step_dir)
    path = step_dir / CHECKSUMS_FILE
    if not path.exists():
        return False
    try:
        files = json.loads(path.read_text())["files"]
    except (ValueError, KeyError, TypeError) as error:
        raise CorruptCheckpointError(f"{path} is unreadable ({error})") from None
    for name, expected in sorted(files.items()):
        file = step_dir / name
        if not file.is_file():
            raise CorruptCheckpointError(f"{file} is missing")
        size = file.stat().st_size
        if size != expected["bytes"]:
            raise CorruptCheckpointError(
                f"{file} has {size} bytes where {expected['bytes']} were saved"
            )
        if _hash_file(file) != expected["sha256"]:
            raise CorruptCheckpointError(f"{file} does not match its saved SHA-256")
    return True


def save_checkpoint(manager: ocp.CheckpointManager, state: TrainState, iterator) -> None:
    """Saves `state` and the iterator at `state.step`, waits until orbax has written
    them, and records their checksums (process 0).

    Raises:
      DiskFullError: the disk is full (or the quota used up). What this save wrote is
        removed; the checkpoints saved before are left as they were (the newest is named).
    """
    import grain

    step = int(jax.device_get(state.step))
    try:
        with _orbax_quiet_about_full_disk():
            manager.save(
                step,
                args=ocp.args.Composite(
                    state=ocp.args.StandardSave(state),
                    data=grain.checkpoint.CheckpointSave(iterator),
                ),
                force=True,
            )
            # The files are hashed as orbax left them, so saving cannot overlap the next steps.
            manager.wait_until_finished()
        if jax.process_index() == 0:
            record_checksums(step_directory(manager, step))
    except Exception as error:
        if no_space_error(error) is None:
            raise
        raise DiskFullError(_unsaved_for_lack_of_space(manager, step)) from None


def _unsaved_for_lack_of_space(manager: ocp.CheckpointManager, step: int) -> str:
    """Removes what a save of `step` that ran out of space wrote (orbax's temporary folder,
    or the step orbax finished but without its checksums) and says what is kept."""
    step_dir = step_directory(manager, step)
    # Orbax's threads of the failed save end before its files are removed from under them.
    with _orbax_quiet_about_full_disk(), contextlib.suppress(Exception):
        manager.wait_until_finished()
    if jax.process_index() == 0:
        partial = list(step_dir.parent.glob(f"{step}{ocp.utils.TMP_DIR_SUFFIX}*"))
        if not (step_dir / CHECKSUMS_FILE).exists():
            partial.append(step_dir)
        for path in partial:
            shutil.rmtree(path, ignore_errors=True)
    manager.reload()
    kept = [saved for saved in manager.all_steps() if saved != step]
    newest = f"newest: step {max(kept)}" if kept else "there were none"
    return (
        f"disk full: no space left in {step_dir.parent} to save the checkpoint of step "
        f"{step}; its partial files are removed and the checkpoints saved before are kept "
        f"({newest}). Free space, then relaunch the same command to resume"
    )


@contextlib.contextmanager
def _orbax_quiet_about_full_disk() -> Iterator[None]:
    """Orbax logs a failed write with its traceback once per thread it passes through;
    on a full disk `save_checkpoint` says it in one line instead. Other logs pass."""

    def keep(record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        return error is None or no_space_error(error) is None

    logger = logging.getLogger("absl")
    logger.addFilter(keep)
    try:
        yield
    finally:
        logger.removeFilter(keep)


def _on_these_devices(leaf) -> jax.ShapeDtypeStruct:
    """A restore target for `leaf`: its shape, dtype and sharding, or, where it has no
    sharding (an abstract or host value), this process's first device. A checkpoint saved
    over another number of devices (`--cpu_devices`) restores onto these."""
    struct = ocp.utils.to_shape_dtype_struct(leaf)
    if getattr(struct, "sharding", None) is None:
        sharding = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
        struct = jax.ShapeDtypeStruct(struct.shape, struct.dtype, sharding=sharding)
    return struct


class Restored(NamedTuple):
    """What `restore_intact_checkpoint` found."""

    state: TrainState
    step: int
    skipped: dict[int, str]  # newer steps that were damaged -> why


def checkpointed_steps(manager: ocp.CheckpointManager, step: int | None = None) -> list[int]:
    """The steps a restore tries: every step the manager holds, newest first, or [step].

    Raises:
      gld.arguments.MissingInputError (a FileNotFoundError): the manager holds no
        checkpoint, or not `step`.
    """
    directory = Path(str(manager.directory))
    available = sorted(manager.all_steps(), reverse=True)
    if step is not None and step not in available:
        raise MissingInputError(
            f"no checkpoint of step {step} in {directory}; available: {sorted(available)}"
        )
    if not available:
        raise MissingInputError(f"no checkpoint in {directory}")
    return [step] if step is not None else available


def restore_intact_checkpoint(
    manager: ocp.CheckpointManager,
    state: TrainState,
    iterator=None,
    step: int | None = None,
    *,
    print_fn: Callable[[str], None] = checkpoint_warning,
) -> Restored:
    """Restores the newest intact checkpoint (or exactly `step`) into the structure and
    shardings of `state`, and the iterator's position if one is given.

    Each candidate is verified against its checksums, then restored; a damaged one is
    skipped and reported through `print_fn`, naming the file or the error.

    Raises:
      gld.arguments.MissingInputError (a FileNotFoundError): the manager holds no
        checkpoint (or not `step`).
      CorruptCheckpointError: no checkpoint is intact (`step` given: that one is not);
        every step's fault is listed. Nothing is deleted.
    """
    import grain

    directory = Path(str(manager.directory))
    manager.reload()  # another process may have saved or moved steps
    candidates = checkpointed_steps(manager, step)
    abstract = jax.tree_util.tree_map(_on_these_devices, state)
    skipped: dict[int, str] = {}
    for candidate in candidates:
        step_dir = step_directory(manager, candidate)
        try:
            verified = verify_checksums(step_dir)
        except CorruptCheckpointError as error:
            skipped[candidate] = str(error)
            print_fn(f"checkpoint step {candidate} skipped: {error}")
            continue
        if not verified:
            print_fn(
                f"checkpoint step {candidate} has no {CHECKSUMS_FILE} (written by an earlier "
                "gld version, or a run stopped while saving it): restored unverified"
            )
        items = {"state": ocp.args.StandardRestore(abstract)}
        if iterator is not None:
            items["data"] = grain.checkpoint.CheckpointRestore(iterator)
        try:
            restored = manager.restore(candidate, args=ocp.args.Composite(**items))
        except Exception as error:  # orbax and tensorstore raise many kinds on bad files
            reason = f"restoring {step_dir} failed: {_short_error(error)}"
            skipped[candidate] = reason
            print_fn(f"checkpoint step {candidate} skipped: {reason}")
            continue
        if skipped:
            print_fn(
                f"restored checkpoint step {candidate}, the newest intact one "
                f"(skipped: {sorted(skipped, reverse=True)})"
            )
        return Restored(restored["state"], candidate, skipped)
    faults = "; ".join(f"step {s}: {why}" for s, why in skipped.items())
    if step is not None:
        raise CorruptCheckpointError(
            f"checkpoint step {step} in {directory} is damaged ({faults}); nothing was deleted"
        )
    raise CorruptCheckpointError(
        f"no checkpoint in {directory} is intact ({faults}). Nothing was deleted: restore "
        "the files from a copy, or move the damaged steps away to start from an older one"
    )


def _short_error(error: BaseException) -> str:
    """The first line of an error and of what caused it (tensorstore's own errors name the
    file; orbax's wrapper adds a long store description, cut here)."""
    parts = []
    while error is not None and len(parts) < 3:
        text = str(error).split(" See full TensorStore details")[0].strip()
        parts.append(f"{type(error).__name__}: {text.splitlines()[0] if text else ''}"[:400])
        error = error.__cause__ or error.__context__
    return "; caused by ".join(parts)


def restore_checkpoint(
    manager: ocp.CheckpointManager,
    state: TrainState,
    iterator=None,
    step: int | None = None,
    *,
    print_fn: Callable[[str], None] = checkpoint_warning,
) -> TrainState:
    """Restores the newest intact (or given) step into the structure/shardings of
    `state`; see `restore_intact_checkpoint`."""
    return restore_intact_checkpoint(manager, state, iterator, step, print_fn=print_fn).state


def move_aside(workdir: str | Path, manager: ocp.CheckpointManager, steps) -> list[Path]:
    """Moves damaged checkpoints out of the manager's directory into
    `<workdir>/corrupt_checkpoints/<step>-<time>` (kept for inspection, never deleted),
    so that training can save those steps again."""
    target_dir = Path(workdir) / CORRUPT_CHECKPOINTS_DIR
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    moved = []
    for step in sorted(steps):
        target_dir.mkdir(parents=True, exist_ok=True)
        target = target_dir / f"{step}-{stamp}"
        suffix = 1
        while target.exists():
            target, suffix = target_dir / f"{step}-{stamp}-{suffix}", suffix + 1
        os.replace(step_directory(manager, step), target)
        moved.append(target)
    manager.reload()
    return moved
