"""A run's directory: checkpoints, the stored configuration, the metrics log, its lock.

    <workdir>/train.lock        held (fcntl.flock) by the training process; names its owner
    <workdir>/config.json       the TrainConfig, the architecture and the run's history
    <workdir>/checkpoints/      orbax: the TrainState ("state") and the grain iterator ("data")
        <step>/checksums.json   SHA-256 and size of every file of that checkpoint
    <workdir>/corrupt_checkpoints/<step>-<time>/  damaged checkpoints a resume moved aside
    <workdir>/metrics.jsonl     one JSON line per (step, split)
    <workdir>/tensorboard/      the same scalars for TensorBoard
    <workdir>/compile_cache/    the compiled programs a launcher keeps (`keep_compiled_programs`)

The lock (`gld.runs.lock`), the verified checkpoints (`gld.runs.checkpoints`) and the
metrics log (`gld.runs.metrics_log`) have modules of their own; this one holds the
stored configuration, the trainer's hold on its workdir (`held_run`) and loads a trained
run.

The hold. A trainer checks its options and the stored config (reading only), then takes
the lock before its costly start-up (the state, the data, compiling), so that a second
launch is refused before it builds anything, and checks the stored config again under
the lock. On a new workdir the lock's file is thus the first thing written: a launch
that fails after taking it (in the start-up, before its first step) leaves the folder
with an empty `train.lock` and nothing else (but `compile_cache/`, when its launcher
keeps the compiled programs, with what it compiled).

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

`load_trained` gives back the model, its trained variables and the run's config.
"""

from __future__ import annotations

import contextlib
import dataclasses
import datetime
import json
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any, NamedTuple

import flax.linen as nn
import jax

from gld.arguments import ArgumentError, MissingInputError
from gld.files import write_atomically
from gld.models import registry
from gld.runs import config as config_lib
from gld.runs import state as state_lib
from gld.runs.checkpoints import (
    CHECKPOINTS_DIR,
    CORRUPT_CHECKPOINTS_DIR,
    checkpoint_manager,
    checkpoint_warning,
    restore_intact_checkpoint,
)
from gld.runs.lock import LOCK_FILE, training_lock
from gld.runs.metrics_log import METRICS_FILE

CONFIG_FILE = "config.json"
COMPILE_CACHE_DIR = "compile_cache"
# Names a launcher's records may not take: the trainer owns them.
RESERVED_NAMES = frozenset(
    {
        CONFIG_FILE,
        METRICS_FILE,
        LOCK_FILE,
        CHECKPOINTS_DIR,
        CORRUPT_CHECKPOINTS_DIR,
        COMPILE_CACHE_DIR,
        "tensorboard",
    }
)
# Programs that compile faster than this are compiled again rather than kept.
_KEPT_COMPILE_SECONDS = 0.5
# The dataset a run was trained on cannot change under its checkpoints.
FIXED_OPTIONS = ("dataset", "height", "width")


@contextlib.contextmanager
def held_run(workdir: str | Path, check: Callable[[], Any]) -> Iterator[Any]:
    """A trainer's hold on its workdir, taken before its costly start-up (the state, the
    data, compiling) so that a second launch is refused before it builds anything: the
    lock taken, then `check()` run again under it (the previous holder may have changed
    the stored config); yields what `check` returned. The lock is released on exit.

    Raises:
      gld.runs.lock.WorkdirLockedError: another process holds the workdir.
    """
    with training_lock(workdir):
        yield check()


def keep_compiled_programs(directory: str | Path) -> None:
    """Keeps this process's compiled programs in `<directory>/compile_cache` (JAX's
    persistent compilation cache), and loads them from there rather than compile them
    again: a later use in this process (the final evaluation runs the periodic one's
    program), a relaunch on the same directory (a resumed run, `experiments.evaluate`)
    or, for a suite's directory, its other runs of one program. Programs that compile in
    under half a second are not kept. JAX sets its cache up at the first compilation
    after this call and keeps that directory for the rest of the process; only process 0
    of a multi-process run writes to it. JAX's cache keys hold the cache's own path, so a
    workdir moved elsewhere compiles its programs again.
    """
    jax.config.update("jax_compilation_cache_dir", str(Path(directory) / COMPILE_CACHE_DIR))
    jax.config.update("jax_persistent_cache_min_compile_time_secs", _KEPT_COMPILE_SECONDS)


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
        saved_arch = {"model": name, **registry.complete_stored_config(name, saved_arch)}
    return saved_arch


def stored_architecture(workdir: str | Path) -> dict[str, Any] | None:
    """The architecture a workdir's run was trained with ({"model": name, **options},
    the options it predates filled in as it was trained); None when it stores none."""
    previous = _read_stored(Path(workdir))
    return None if previous is None else _completed_architecture(previous)


def architecture_refusal(
    workdir: Path, stored: Mapping[str, Any], current: Mapping[str, Any], what: str = "run"
) -> str | None:
    """The one line that refuses a run of architecture `current` in a workdir whose run
    has architecture `stored` (None when they agree). Another model is the decisive
    difference and is named alone (the options of two models do not compare); for the
    same model each differing option is named. An option the stored run does not record
    (it predates it) is no difference."""
    if stored.get("model") != current.get("model"):
        return (
            f"--model={current.get('model')}: workdir {workdir} holds a {what} of model "
            f"{stored.get('model')!r}; use another --workdir, or --model={stored.get('model')}"
        )
    differing = sorted(k for k in stored if k != "model" and stored[k] != current.get(k))
    if not differing:
        return None
    details = ", ".join(f"--{k}={stored[k]!r} there, {current.get(k)!r} now" for k in differing)
    return (
        f"workdir {workdir} holds a {what} of another architecture ({details}); use "
        "another --workdir or the original flags"
    )


def check_run_config(
    workdir: str | Path, config: config_lib.TrainConfig
) -> dict[str, tuple[Any, Any]] | None:
    """Checks `config` against the workdir's stored config, reading only.

    Returns:
      None when the workdir stores no config; else the options that differ, as
      {name: (stored, now)} (model options as "model_config.<name>").

    Raises:
      ArgumentError: the workdir holds a run of another architecture, dataset or
        resolution (`architecture_refusal`; the fixed options each named).
    """
    workdir = Path(workdir)
    previous = _read_stored(workdir)
    if previous is None:
        return None
    saved_arch = _completed_architecture(previous)
    current_arch = json.loads(json.dumps(config.architecture()))
    refusal = architecture_refusal(workdir, saved_arch, current_arch)
    if refusal:
        raise ArgumentError(refusal)
    for key in FIXED_OPTIONS:
        if previous.get("config", {}).get(key) not in (None, getattr(config, key)):
            raise ArgumentError(
                f"--{key}={getattr(config, key)}: workdir {workdir} was trained on "
                f"{key}={previous['config'][key]!r}; use another --workdir or the original flags"
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
        raise MissingInputError(f"{path} not found: is {workdir} a gld training workdir?")
    return config_lib.from_stored(json.loads(path.read_text())["config"])


class Trained(NamedTuple):
    """A trained model from a workdir."""

    model: nn.Module
    variables: dict
    config: config_lib.TrainConfig
    step: int


def restore_trained(
    workdir: str | Path,
    step: int | None = None,
    *,
    print_fn: Callable[[str], None] = checkpoint_warning,
) -> Trained:
    """The model, its trained variables, the run's config and the step restored (the
    newest intact checkpoint, or exactly `step`)."""
    workdir = Path(workdir)
    config = load_run_config(workdir)
    model = registry.make_model(config.model, **config.model_config)
    optimizer = config.optimizer()
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
    workdir: str | Path,
    step: int | None = None,
    *,
    print_fn: Callable[[str], None] = checkpoint_warning,
) -> tuple[nn.Module, dict, config_lib.TrainConfig]:
    """The model, its trained variables and the run's config, from a workdir (the newest
    intact checkpoint, or exactly `step`; `restore_trained` also says which step)."""
    model, variables, config, _ = restore_trained(workdir, step, print_fn=print_fn)
    return model, variables, config
