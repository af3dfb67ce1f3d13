"""A run's directory: checkpoints, the stored configuration, the metrics log, its lock.

    <workdir>/train.lock        held (fcntl.flock) by the training process; names its owner
    <workdir>/config.json       the TrainConfig, the architecture and the run's history
    <workdir>/checkpoints/      orbax: the TrainState ("state") and the grain iterator ("data")
        <step>/checksums.json   SHA-256 and size of every file of that checkpoint
    <workdir>/corrupt_checkpoints/<step>-<time>/  damaged checkpoints a resume moved aside
    <workdir>/metrics.jsonl     one JSON line per (step, split)
    <workdir>/tensorboard/      the same scalars for TensorBoard

One training process per workdir. `WorkdirLock` takes an exclusive `flock` on
`train.lock` and writes its owner (pid, host, start time, command line) into it; a second
launch is refused with that owner's name. The kernel drops the lock when its process
dies, so a killed run never leaves it stuck. In a multi-process run only process 0 takes
it; readers (evaluation, inspection) need none.

The stored configuration. `check_run_config` only reads: it refuses a workdir trained
with another architecture, dataset or resolution and returns the options that differ
from the stored ones. The trainer writes `config.json` (and the launcher's records, such
as `flags.txt`) only after everything has been validated, each file atomically (a
temporary file in the workdir, then `os.replace`): on a new workdir before the first
step; on an existing one, with the first checkpoint this launch saves, and only if
something differs. A launch that trains no step (finished run, refusal, a failure
before the first checkpoint) leaves them as they were. When the options differ, the
stored config becomes the new one and `config.json`'s "history" list gains an entry
{"step": the step training resumed from, "time", "changed": {option: {"from", "to"}}};
reading the entries in order gives the options in force over each range of steps.

The metrics log holds one line per (step, split). Steps logged after the last checkpoint
are trained again on resume, so `drop_metrics_after` removes the lines with step > the
restored step first (an atomic rewrite). TensorBoard gets a new event file per launch
and shows the latest value written for a step.

Checkpoints are verified. `save_checkpoint` waits for orbax to finish writing a step and
records the SHA-256 and size of each of its files; `restore_checkpoint` (and with it
`load_trained` and resuming) checks them before restoring. A damaged checkpoint (a file
changed, truncated or missing, or one orbax fails to restore) is skipped, naming the
file, and the newest intact one is used; if none is intact, `CorruptCheckpointError`
lists every step's fault and nothing is deleted. A resume moves the damaged newer steps
to `corrupt_checkpoints/` (kept, never deleted) so that it can save those steps again;
`load_trained` moves nothing. Checkpoints written before checksums existed are restored
unverified, with a `CheckpointWarning`. Hashing needs the files on a local or mounted
file system, and makes each save wait until orbax has written it.

`load_trained` gives back the model, its trained variables and the run's config.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import fcntl
import hashlib
import json
import math
import os
import shlex
import socket
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax
import orbax.checkpoint as ocp

from gld import config as config_lib
from gld import model as model_lib
from gld import state as state_lib
from gld.state import TrainState

CONFIG_FILE = "config.json"
METRICS_FILE = "metrics.jsonl"
LOCK_FILE = "train.lock"
CHECKSUMS_FILE = "checksums.json"
CHECKPOINTS_DIR = "checkpoints"
CORRUPT_CHECKPOINTS_DIR = "corrupt_checkpoints"
# Names a launcher's records may not take: the trainer owns them.
RESERVED_NAMES = frozenset(
    {CONFIG_FILE, METRICS_FILE, LOCK_FILE, CHECKPOINTS_DIR, CORRUPT_CHECKPOINTS_DIR, "tensorboard"}
)
# The dataset a run was trained on cannot change under its checkpoints.
FIXED_OPTIONS = ("dataset", "height", "width")


class WorkdirLockedError(RuntimeError):
    """Another training process holds the workdir."""


class CorruptCheckpointError(ValueError):
    """A checkpoint's files do not match what was saved, or no checkpoint is intact."""


class CheckpointWarning(UserWarning):
    """A checkpoint was skipped, or restored without checksums to verify it."""


def _warn(message: str) -> None:
    warnings.warn(message, CheckpointWarning, stacklevel=3)


def write_atomically(path: Path, text: str | bytes) -> None:
    """Writes `text` (or bytes) to `path` through a temporary file in the same directory
    and `os.replace`, so a reader (or a killed writer) sees the old file or the new one."""
    path = Path(path)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb" if isinstance(text, bytes) else "w") as stream:
            stream.write(text)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


# ---------------------------------------------------------------------------- the lock


class WorkdirLock:
    """An exclusive lock on `<workdir>/train.lock`, naming its owner in the file.

    Use as a context manager, or `acquire()` / `release()`. The lock belongs to the open
    file, so the kernel releases it when the owning process exits, however it exits.
    """

    def __init__(self, workdir: str | Path):
        self.path = Path(workdir) / LOCK_FILE
        self._fd: int | None = None

    def acquire(self) -> None:
        """Takes the lock, creating the workdir if needed.

        Raises:
          WorkdirLockedError: another process holds it (its pid, host, start time and
            command line are in the message).
        """
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            owner = _describe_owner(os.pread(fd, 1 << 16, 0))
            os.close(fd)
            raise WorkdirLockedError(
                f"workdir {self.path.parent} is in use by another training run ({owner}); "
                f"wait for it to end or use another --workdir (lock file {self.path})"
            ) from None
        owner = {
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "started": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
            "command": _command_line(),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(owner) + "\n").encode(), 0)
        self._fd = fd

    def release(self) -> None:
        """Releases the lock (a no-op when not held); the file stays, emptied."""
        if self._fd is None:
            return
        # Emptied first, so the file never names a process that no longer holds it.
        os.ftruncate(self._fd, 0)
        fcntl.flock(self._fd, fcntl.LOCK_UN)
        os.close(self._fd)
        self._fd = None

    def __enter__(self) -> WorkdirLock:
        self.acquire()
        return self

    def __exit__(self, *exc_info) -> None:
        self.release()


def _command_line() -> str:
    """This process's command line as typed (`python -m ...`), where /proc has it."""
    try:
        arguments = Path("/proc/self/cmdline").read_bytes().rstrip(b"\0").split(b"\0")
        return shlex.join(argument.decode(errors="replace") for argument in arguments)
    except OSError:
        return shlex.join([sys.executable, *sys.argv])


def _describe_owner(content: bytes) -> str:
    try:
        owner = json.loads(content)
        return (
            f"pid {owner['pid']} on host {owner['host']}, started {owner['started']}, "
            f"command: {owner['command']}"
        )
    except (ValueError, KeyError, TypeError):
        return "its owner has not recorded itself yet"


@contextlib.contextmanager
def training_lock(workdir: str | Path) -> Iterator[None]:
    """`WorkdirLock` on process 0; other processes of a multi-process run share the
    workdir under process 0's lock."""
    if jax.process_index() != 0:
        yield
        return
    with WorkdirLock(workdir):
        yield


@contextlib.contextmanager
def held_run(workdir: str | Path, keep: int, check: Callable[[], Any]) -> Iterator[tuple[Any, Any]]:
    """A trainer's hold on its workdir: the lock taken, `check()` run again under it (the
    previous holder may have changed the stored config) before the checkpoint manager
    opens; yields (what `check` returned, the manager). On exit pending saves finish and
    the manager closes, then the lock is released."""
    with training_lock(workdir):
        checked = check()
        manager = checkpoint_manager(workdir, keep=keep)
        try:
            yield checked, manager
        finally:
            manager.wait_until_finished()
            manager.close()


# ------------------------------------------------------------------ the stored config


def _stored_config(config: config_lib.TrainConfig) -> dict[str, Any]:
    """The "config" entry of config.json: plain JSON values."""
    stored = dataclasses.asdict(config)
    # Every architecture value is written out; the speed-only formulation only if given.
    stored["model_config"] = {
        **{k: v for k, v in config.architecture().items() if k != "model"},
        **config.model_config,
    }
    return json.loads(json.dumps(stored))


def _flatten(values: Mapping[str, Any]) -> dict[str, Any]:
    flat = {}
    for key, value in values.items():
        if key == "model_config":
            flat.update({f"model_config.{k}": v for k, v in value.items()})
        else:
            flat[key] = value
    return flat


def _read_stored(workdir: Path) -> dict[str, Any] | None:
    path = workdir / CONFIG_FILE
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path} is not valid JSON ({error}); it was not written by gld") from None


def _completed_architecture(stored: Mapping[str, Any]) -> dict[str, Any]:
    saved_arch = dict(stored.get("architecture", {}))
    if "model" in saved_arch:
        name = saved_arch.pop("model")
        saved_arch = {"model": name, **model_lib.complete_stored_config(name, saved_arch)}
    return saved_arch


def stored_architecture(workdir: str | Path) -> dict[str, Any] | None:
    """The architecture a workdir's run was trained with ({"model": name, **options},
    the options it predates filled in as it was trained); None when it stores none."""
    previous = _read_stored(Path(workdir))
    return None if previous is None else _completed_architecture(previous)


def check_run_config(
    workdir: str | Path, config: config_lib.TrainConfig
) -> dict[str, tuple[Any, Any]] | None:
    """Checks `config` against the workdir's stored config, reading only.

    Returns:
      None when the workdir stores no config; else the options that differ, as
      {name: (stored, now)} (model options as "model_config.<name>").

    Raises:
      ValueError: the workdir holds a run of another architecture, dataset or
        resolution (every differing value is named).
    """
    workdir = Path(workdir)
    previous = _read_stored(workdir)
    if previous is None:
        return None
    saved_arch = _completed_architecture(previous)
    current_arch = json.loads(json.dumps(config.architecture()))
    differing = sorted(
        key
        for key in set(saved_arch) | set(current_arch)
        if saved_arch.get(key) != current_arch.get(key)
    )
    if differing:
        details = ", ".join(
            f"{k}: {saved_arch.get(k)!r} in the workdir vs {current_arch.get(k)!r} now"
            for k in differing
        )
        raise ValueError(
            f"workdir {workdir} holds a run of a different architecture ({details}); "
            "use another --workdir or the original flags"
        )
    for key in FIXED_OPTIONS:
        if previous.get("config", {}).get(key) not in (None, getattr(config, key)):
            raise ValueError(
                f"workdir {workdir} was trained on {key}={previous['config'][key]!r}, "
                f"not {getattr(config, key)!r}"
            )
    # Compared in today's form, so renamed or later-added fields are no difference.
    stored = _flatten(_stored_config(config_lib.from_stored(previous["config"])))
    current = _flatten(_stored_config(config))
    return {
        key: (stored.get(key), current.get(key))
        for key in sorted(set(stored) | set(current))
        if stored.get(key) != current.get(key)
    }


def describe_changes(changes: Mapping[str, tuple[Any, Any]]) -> str:
    """The changes as one line, e.g. `learning_rate 0.001 -> 0.0001, steps 4 -> 8`."""
    return ", ".join(f"{key} {old!r} -> {new!r}" for key, (old, new) in changes.items())


def check_records(records: Mapping[str, str] | None) -> dict[str, str]:
    """Checks a launcher's records (file name -> text): plain names the trainer does
    not own. Raises ValueError naming a bad one."""
    records = dict(records or {})
    for name, text in records.items():
        if not isinstance(name, str) or Path(name).name != name or name in ("", ".", ".."):
            raise ValueError(f"record name {name!r} is not a plain file name")
        if name in RESERVED_NAMES:
            raise ValueError(f"record name {name!r} is the trainer's own; choose another")
        if not isinstance(text, str):
            raise ValueError(f"record {name!r} must be text, got {type(text).__name__}")
    return records


def records_differ(workdir: str | Path, records: Mapping[str, str]) -> bool:
    """Whether any record's file is missing or holds other text."""
    workdir = Path(workdir)
    return any(
        not (workdir / name).is_file() or (workdir / name).read_text() != text
        for name, text in records.items()
    )


def write_run_config(
    workdir: str | Path,
    config: config_lib.TrainConfig,
    *,
    step: int | None = None,
    records: Mapping[str, str] | None = None,
) -> dict[str, tuple[Any, Any]] | None:
    """Checks `config` against the workdir (`check_run_config`), then writes `records`
    and `config.json`, each atomically (process 0 only).

    When a config is already stored and options differ, `config.json`'s "history" gains
    {"step": step, "time", "changed"} (without "step" when it is None).

    Returns:
      What `check_run_config` returned.
    """
    workdir = Path(workdir)
    records = check_records(records)
    changes = check_run_config(workdir, config)
    if jax.process_index() != 0:
        return changes
    workdir.mkdir(parents=True, exist_ok=True)
    history = list((_read_stored(workdir) or {}).get("history", []))
    if changes:
        entry = {"step": step} if step is not None else {}
        entry["time"] = datetime.datetime.now().astimezone().isoformat(timespec="seconds")
        entry["changed"] = {key: {"from": old, "to": new} for key, (old, new) in changes.items()}
        history.append(entry)
    payload = {"architecture": config.architecture(), "config": _stored_config(config)}
    if history:
        payload["history"] = history
    for name, text in records.items():
        write_atomically(workdir / name, text)
    # config.json last: it is the record the others go with.
    write_atomically(workdir / CONFIG_FILE, json.dumps(payload, indent=2, sort_keys=True) + "\n")
    return changes


def load_run_config(workdir: str | Path) -> config_lib.TrainConfig:
    """The TrainConfig a workdir was trained with."""
    path = Path(workdir) / CONFIG_FILE
    if not path.exists():
        raise FileNotFoundError(f"{path} not found: is {workdir} a gld training workdir?")
    return config_lib.from_stored(json.loads(path.read_text())["config"])


# ------------------------------------------------------------------------ checkpoints


def checkpoint_manager(
    workdir: str | Path, *, keep: int = 2, every: int = 1
) -> ocp.CheckpointManager:
    """The run's orbax manager: items "state" (TrainState) and "data" (grain iterator)."""
    import grain

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
    them, and records their checksums (process 0)."""
    import grain

    step = int(jax.device_get(state.step))
    manager.save(
        step,
        args=ocp.args.Composite(
            state=ocp.args.StandardSave(state), data=grain.checkpoint.CheckpointSave(iterator)
        ),
        force=True,
    )
    # The files are hashed as orbax left them, so saving cannot overlap the next steps.
    manager.wait_until_finished()
    if jax.process_index() == 0:
        record_checksums(step_directory(manager, step))


class Restored(NamedTuple):
    """What `restore_intact_checkpoint` found."""

    state: TrainState
    step: int
    skipped: dict[int, str]  # newer steps that were damaged -> why


def restore_intact_checkpoint(
    manager: ocp.CheckpointManager,
    state: TrainState,
    iterator=None,
    step: int | None = None,
    *,
    print_fn: Callable[[str], None] = _warn,
) -> Restored:
    """Restores the newest intact checkpoint (or exactly `step`) into the structure and
    shardings of `state`, and the iterator's position if one is given.

    Each candidate is verified against its checksums, then restored; a damaged one is
    skipped and reported through `print_fn`, naming the file or the error.

    Raises:
      FileNotFoundError: the manager holds no checkpoint (or not `step`).
      CorruptCheckpointError: no checkpoint is intact (`step` given: that one is not);
        every step's fault is listed. Nothing is deleted.
    """
    import grain

    directory = Path(str(manager.directory))
    manager.reload()  # another process may have saved or moved steps
    available = sorted(manager.all_steps(), reverse=True)
    if step is not None and step not in available:
        raise FileNotFoundError(
            f"no checkpoint of step {step} in {directory}; there are {sorted(available)}"
        )
    if not available:
        raise FileNotFoundError(f"no checkpoint in {directory}")
    candidates = [step] if step is not None else available
    abstract = jax.tree_util.tree_map(ocp.utils.to_shape_dtype_struct, state)
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
    print_fn: Callable[[str], None] = _warn,
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


class Trained(NamedTuple):
    """A trained model from a workdir."""

    model: nn.Module
    variables: dict
    config: config_lib.TrainConfig
    step: int


def restore_trained(
    workdir: str | Path, step: int | None = None, *, print_fn: Callable[[str], None] = _warn
) -> Trained:
    """The model, its trained variables, the run's config and the step restored (the
    newest intact checkpoint, or exactly `step`)."""
    workdir = Path(workdir)
    config = load_run_config(workdir)
    model = model_lib.make_model(config.model, **config.model_config)
    optimizer = state_lib.config_optimizer(config)
    # Shapes and dtypes are all a restore needs: building the real initial state would
    # compile every initialiser (seconds) only to be overwritten.
    template = jax.eval_shape(
        lambda: state_lib.create_train_state(
            model, optimizer, config.height, config.width, config.seed
        )
    )
    manager = checkpoint_manager(workdir)
    try:
        restored = restore_intact_checkpoint(manager, template, step=step, print_fn=print_fn)
    finally:
        manager.close()
    return Trained(model, restored.state.variables(), config, restored.step)


def load_trained(
    workdir: str | Path, step: int | None = None, *, print_fn: Callable[[str], None] = _warn
) -> tuple[nn.Module, dict, config_lib.TrainConfig]:
    """The model, its trained variables and the run's config, from a workdir (the newest
    intact checkpoint, or exactly `step`; `restore_trained` also says which step)."""
    model, variables, config, _ = restore_trained(workdir, step, print_fn=print_fn)
    return model, variables, config


# ------------------------------------------------------------------------- metrics


def read_metrics(workdir: str | Path) -> list[dict[str, Any]]:
    """The records of a run's metrics.jsonl, in order (none without the file); a line cut
    short by a killed writer is skipped."""
    path = Path(workdir) / METRICS_FILE
    if not path.exists():
        return []
    records = []
    for line in path.read_text().splitlines():
        try:
            records.append(json.loads(line))
        except ValueError:
            continue
    return records


def drop_metrics_after(workdir: str | Path, step: int) -> int:
    """Removes the metrics.jsonl lines of steps after `step` (and any line cut short by a
    killed writer), rewriting the file atomically; returns how many were removed."""
    path = Path(workdir) / METRICS_FILE
    if not path.exists():
        return 0
    kept, dropped = [], 0
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            record_step = json.loads(line)["step"]
        except (ValueError, KeyError, TypeError):
            dropped += 1
            continue
        if record_step > step:
            dropped += 1
        else:
            kept.append(line + "\n")
    if dropped:
        write_atomically(path, "".join(kept))
    return dropped


class MetricsLogger:
    """metrics.jsonl + TensorBoard, written by process 0 only."""

    def __init__(self, workdir: Path):
        self.enabled = jax.process_index() == 0
        self.path = Path(workdir) / METRICS_FILE
        self.writer = None
        if self.enabled:
            from tensorboardX import SummaryWriter

            self.writer = SummaryWriter(str(Path(workdir) / "tensorboard"))

    def write(self, step: int, values: dict[str, float], prefix: str = "train") -> None:
        if not self.enabled:
            return
        record = {"step": step, "split": prefix, **values}
        with self.path.open("a") as stream:
            stream.write(json.dumps(record) + "\n")
        for name, value in values.items():
            if isinstance(value, int | float) and math.isfinite(value):
                self.writer.add_scalar(f"{prefix}/{name}", value, step)
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
