"""Flags and set-up shared by the launchers (train, evaluate, inspect_filters, compare).

The flags of a run's options are made by `define_option_flags` from the options'
fields (`TrainConfig`, `GlobalLocal`, `FlowTrainConfig`, `FlowNet`); this module chooses
which a launcher has.

A launcher ends with `common.run(main)` (`data.command_line.run`): a user's mistake ends it
with one line on stderr, no traceback and no help text.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from absl import flags

from data.command_line import parse_flags, run  # noqa: F401  (every launcher's ending)

FLAGS = flags.FLAGS


def define_truth_resolution_flag() -> None:
    """--truth_resolution, as evaluate and compare read it."""
    from gld.evaluation import metrics

    flags.DEFINE_enum(
        "truth_resolution",
        None,
        list(metrics.TRUTH_RESOLUTIONS),
        "Where the ground truth is scored: file (the resolution of the DeMoN files the "
        "split was built from, in --manual_dir or where the build found them, read by "
        "example id, each prediction resized by nearest neighbour, as DeMoN evaluates; "
        "demon/* datasets only) or record (the records' resolution). Default: file for "
        "demon/* datasets, record for the others.",
    )


def define_data_flags(default_dataset: str = "gld_scenes/small") -> None:
    flags.DEFINE_string(
        "dataset", default_dataset, "TFDS dataset with config, e.g. gld_scenes/small, demon/sun3d."
    )
    flags.DEFINE_string("data_dir", None, "Where built datasets live (default: ./datasets).")
    flags.DEFINE_string("manual_dir", None, "Manual-download dir (DeMoN .h5 files).")


def define_flow_source_flag() -> None:
    """--flow_source for launchers that use a trained workdir (default: the workdir's)."""
    from gld.runs.config import FLOW_SOURCES

    flags.DEFINE_enum(
        "flow_source",
        None,
        list(FLOW_SOURCES),
        "Which flow the model is given (default: the workdir's; estimated for a method "
        "without training).",
    )


def define_option_flags(
    fields: Iterable[dataclasses.Field],
    defaults: Mapping[str, Any] | None = None,
    flag_set: flags.FlagValues = FLAGS,
) -> None:
    """One absl flag per option field, typed by its choices or its default, with its help
    and bounds (checked when the command line is parsed, so a bad value stops a launcher
    before it does anything); `defaults` replaces some defaults for one launcher."""
    fields = list(fields)
    defaults = dict(defaults or {})
    # The flags belong to the module that asks for them (a launcher, as `--help` and
    # `--helpfull` list them), not to this one; absl names the main module by its file.
    module_name = sys._getframe(1).f_globals["__name__"]
    module_name = sys.argv[0] if module_name == "__main__" else module_name
    unknown = sorted(set(defaults) - {field.name for field in fields})
    if unknown:
        raise ValueError(f"no option(s) {unknown} to give a default")
    for field in fields:
        name, metadata = field.name, field.metadata
        default = defaults.get(name, field.default)
        help_text = metadata["help"]
        low, high = metadata["at_least"], metadata.get("at_most")
        if metadata["choices"]:
            flags.DEFINE_enum(
                name, default, list(metadata["choices"]), help_text, flag_values=flag_set
            )
        elif isinstance(default, bool):
            flags.DEFINE_bool(
                name, default, help_text, flag_values=flag_set, module_name=module_name
            )
        elif isinstance(default, int):
            flags.DEFINE_integer(
                name, default, help_text, low, high, flag_values=flag_set, module_name=module_name
            )
        elif isinstance(default, float):
            flags.DEFINE_float(
                name, default, help_text, low, high, flag_values=flag_set, module_name=module_name
            )
        elif isinstance(default, list | tuple):
            flags.DEFINE_list(
                name, [str(value) for value in default], help_text, flag_values=flag_set
            )
        else:
            flags.DEFINE_string(
                name, default, help_text, flag_values=flag_set, module_name=module_name
            )
        if metadata["above"] is not None:
            above = metadata["above"]
            flags.register_validator(
                name,
                lambda value, above=above: value is None or value > above,
                message=f"--{name} must be above {above}",
                flag_values=flag_set,
            )


def option_flag_values(
    fields: Iterable[dataclasses.Field], flag_set: flags.FlagValues = FLAGS
) -> dict[str, Any]:
    """The values of the option fields' flags (those defined), lists of numbers as
    numbers; an option left at None (a speed-only choice) is omitted. Raises ValueError
    naming a list flag whose items are not numbers."""
    values = {}
    for field in fields:
        if field.name not in flag_set:
            continue
        value = flag_set[field.name].value
        if isinstance(field.default, list | tuple) and isinstance(value, list):
            value = _numbers(field, value)
        if value is not None:
            values[field.name] = value
    return values


def _numbers(field: dataclasses.Field, items: list[str]) -> list[int | float]:
    kind = type(field.default[0]) if field.default else int
    try:
        return [kind(item) for item in items]
    except ValueError:
        noun = "integers" if kind is int else "numbers"
        raise ValueError(f"{field.name} must be {noun}, got {items}") from None


def define_training_flags(*, exclude: Sequence[str] = (), **defaults: Any) -> None:
    """A flag for every option of `gld.runs.config.TrainConfig` but `exclude`
    (`define_option_flags`); `defaults` replaces some defaults for this launcher
    (the main job's recipe in `experiments.train`)."""
    from gld import options
    from gld.runs import config

    fields = [
        field for field in options.option_fields(config.TrainConfig) if field.name not in exclude
    ]
    define_option_flags(fields, defaults)


def training_options() -> dict[str, Any]:
    """The TrainConfig options given by this launcher's training flags."""
    from gld import options
    from gld.runs import config

    return option_flag_values(options.option_fields(config.TrainConfig))


def define_architecture_flags(**defaults: Any) -> None:
    """A flag for every architecture option of the global-local model
    (`define_option_flags`); `defaults` replace the model's defaults of some options
    for this launcher (the main job's recipe)."""
    from gld import options
    from gld.models.global_local import GlobalLocal

    define_option_flags(options.option_fields(GlobalLocal), defaults)


def architecture_options() -> dict[str, Any]:
    """The global-local model's constructor arguments from the architecture flags (lists
    as numbers; an option left at None, like the speed-only formulation, is omitted)."""
    from absl import app

    from gld import options
    from gld.models.global_local import GlobalLocal

    try:
        return option_flag_values(options.option_fields(GlobalLocal))
    except ValueError as error:
        raise app.UsageError(f"--{error}") from None


def define_flow_net_flags() -> None:
    """Flags of the depth models with a learned flow network (`gld.models.flow_depth`)."""
    flags.DEFINE_string(
        "flow_net_workdir",
        "",
        "global_local_flow_net, flow_net_head: a flow network's run "
        "(experiments.train_flow) to start from; empty: random initialisation.",
    )
    flags.DEFINE_bool(
        "flow_trainable",
        False,
        "global_local_flow_net: fine-tune the flow network with the depth loss (default: fixed).",
    )


def flow_net_options(model_name: str) -> dict[str, Any]:
    """The flow-network flags' values that `model_name` takes (none but for the models of
    `gld.models.flow_depth`)."""
    if model_name == "global_local_flow_net":
        return {
            "flow_net_workdir": FLAGS.flow_net_workdir,
            "flow_trainable": FLAGS.flow_trainable,
        }
    if model_name == "flow_net_head":
        return {"flow_net_workdir": FLAGS.flow_net_workdir}
    return {}


def model_options(model_name: str) -> dict[str, Any]:
    """The constructor arguments of `model_name` from this launcher's flags: the
    architecture flags for the global-local model, the flow-network flags for the models
    of `gld.models.flow_depth`, none for the baselines (their paper's architectures)."""
    if model_name == "global_local":
        return architecture_options()
    return flow_net_options(model_name)


def define_compile_cache_flag(use: str) -> None:
    """--compile_cache: the compiled programs kept in <workdir>/compile_cache
    (`gld.runs.workdir.keep_compiled_programs`); `use` says what this launcher gains."""
    flags.DEFINE_bool(
        "compile_cache",
        True,
        "Keep compiled programs in <workdir>/compile_cache (JAX's persistent cache) and "
        f"load them from there: {use}",
    )


def define_distributed_flags() -> None:
    flags.DEFINE_integer(
        "cpu_devices",
        2,
        "On the CPU, JAX devices the host is split into: each batch is split over them "
        "(data parallelism over the cores). Lowered to the largest count that divides "
        "--batch_size; results differ across counts only by float rounding.",
        lower_bound=1,
    )
    flags.DEFINE_string("coordinator_address", None, "host:port of process 0 (multi-process).")
    flags.DEFINE_integer("num_processes", 1, "Number of JAX processes.", lower_bound=1)
    flags.DEFINE_integer("process_id", 0, "This process's index.", lower_bound=0)
    flags.DEFINE_integer(
        "distributed_timeout",
        300,
        "Seconds a process waits for all the others to join before it gives up.",
        lower_bound=1,
    )
    flags.register_multi_flags_validator(
        ["num_processes", "process_id", "coordinator_address"],
        lambda values: (
            values["num_processes"] == 1
            or (values["process_id"] < values["num_processes"] and values["coordinator_address"])
        ),
        message="a multi-process run needs --coordinator_address and a --process_id below "
        "--num_processes",
    )


def initialise() -> None:
    """Quiet library logs (unless --verbosity is given), split the CPU into --cpu_devices
    devices and start multi-process JAX when --num_processes > 1 (before any device is
    touched).

    JAX aborts the process with a C++ stack trace when the others do not join in time;
    a watchdog stops it a moment earlier with a message saying what to check.
    """
    from absl import logging

    if not FLAGS["verbosity"].present:
        logging.set_verbosity(logging.WARNING)
    if "cpu_devices" in FLAGS:
        from gld import sharding

        count = FLAGS.cpu_devices
        if "batch_size" in FLAGS:
            count = sharding.devices_for_batch(FLAGS.batch_size, count, FLAGS.num_processes)
        sharding.split_cpu_devices(count)
    if "num_processes" in FLAGS and FLAGS.num_processes > 1:
        import threading

        import jax

        count, index, timeout = FLAGS.num_processes, FLAGS.process_id, FLAGS.distributed_timeout
        where = FLAGS.coordinator_address
        print(f"process {index} of {count}: waiting up to {timeout} s for all at {where}")

        def give_up() -> None:
            print(
                f"process {index} of {count}: the {count} processes did not all join at "
                f"{where} within {timeout} s (--distributed_timeout). Start every process "
                f"with the same --coordinator_address and --num_processes={count} and its "
                f"own --process_id in 0..{count - 1}; process 0 must be reachable at {where}.",
                file=sys.stderr,
                flush=True,
            )
            os._exit(3)

        watchdog = threading.Timer(timeout, give_up)
        watchdog.daemon = True
        watchdog.start()
        jax.config.update("jax_cpu_collectives_implementation", "gloo")
        jax.distributed.initialize(
            coordinator_address=where,
            num_processes=count,
            process_id=index,
            initialization_timeout=timeout + 30,
        )
        watchdog.cancel()


def prepare_dataset(dataset: str | None = None, parallel: bool = True):
    """Builds the dataset on first use and returns its TFDS builder.

    With `parallel`, a rendered dataset is built by one process per core (up to 8; its
    records do not depend on the number, `data.gld_scenes`). The processes are forked: a
    caller that may already have run JAX or OpenCV's thread pool passes parallel=False."""
    import os

    import data

    dataset = dataset or FLAGS.dataset
    options = {}
    if parallel and data.parse_name(dataset)[0] == "gld_scenes":
        options["workers"] = max(1, min(len(os.sched_getaffinity(0)), 8))
    return data.prepare(dataset, FLAGS.data_dir, FLAGS.manual_dir, **options)


def dataset_resolution(builder) -> tuple[int, int]:
    """(height, width) of a built gld dataset."""
    height, width = builder.info.features["depth1"].shape
    return int(height), int(width)


def training_data(evaluates: bool):
    """A trainer's data: the dataset built on first use, checked to have a train split
    (and a test split when the run `evaluates`), announced with its resolution.

    Returns:
      (builder, height, width, train source, test source or None).
    """
    from absl import app

    builder = prepare_dataset()
    splits = builder.info.splits
    if "train" not in splits:
        raise app.UsageError(f"{FLAGS.dataset} has no train split: nothing to train on")
    if evaluates and "test" not in splits:
        raise app.UsageError(
            f"{FLAGS.dataset} has no test split to evaluate on; train without evaluation "
            "with --eval_every=0 --nofinal_eval"
        )
    height, width = dataset_resolution(builder)
    counts = ", ".join(
        f"{splits[split].num_examples} {split}" for split in ("train", "test") if split in splits
    )
    print(f"dataset {FLAGS.dataset}: {counts} pairs at {width}x{height}")
    train_source = data_source(builder, "train")
    test_source = data_source(builder, "test") if evaluates else None
    return builder, height, width, train_source, test_source


def dataset_flow_record(builder) -> str:
    """The flow a built dataset stores (its card's "flow_estimator_source": the estimator,
    and a flow network's workdir, step and parameter digest), as JSON: the record an
    export reads to compute the same flow on the robot."""
    from gld import flow as flow_lib

    source = dict(builder.info.metadata.get("flow_estimator_source") or {})
    if "estimator" not in source:
        source["estimator"] = getattr(builder, "flow_estimator", flow_lib.DEFAULT_ESTIMATOR)
    return json.dumps(source, indent=1, sort_keys=True) + "\n"


def flags_file_text() -> str:
    """This run's gld flags (the launcher's, the shared ones and the dataset builders'),
    one per line: a valid --flagfile for the same launcher. Flags that libraries define
    (absl logging, grain, jax) are left out; they are not options of the run."""
    own = ("experiments.", "data.", "gld.")
    lines = []
    for module, module_flags in FLAGS.flags_by_module_dict().items():
        if module == sys.argv[0] or module.startswith(own):
            lines.extend(flag.serialize() for flag in module_flags if flag.name != "flagfile")
    return "\n".join(sorted(line for line in lines if line)) + "\n"


def commit_stamp(*outputs: Path) -> str:
    """The repository's commit, with "+changes" when the tracked files differ from it
    outside `outputs` (the report and the results the suite itself writes)."""

    def git(*args: str) -> str:
        return subprocess.run(
            ["git", *args], capture_output=True, text=True, check=True
        ).stdout.strip()

    try:
        commit = git("rev-parse", "--short", "HEAD")
        top = Path(git("rev-parse", "--show-toplevel")).resolve()
        changed = git("diff", "--name-only", "HEAD").splitlines()
    except (OSError, subprocess.CalledProcessError):
        return ""
    outputs = [path.resolve() for path in outputs]
    dirty = [
        name
        for name in changed
        if not any((top / name).resolve().is_relative_to(path) for path in outputs)
    ]
    return commit + ("+changes" if dirty else "")


def train_config(**values: Any):
    """The TrainConfig of this launcher's training flags and `values`, checked as a whole
    (`TrainConfig.validate`) before anything is built or written: a bad value stops the
    launcher with a usage error naming the option."""
    from absl import app

    from gld.runs import config

    try:
        return config.TrainConfig(**{**training_options(), **values}).validate()
    except ValueError as error:
        raise app.UsageError(f"--{error}") from None


def data_source(builder, split: str):
    """A split's random-access records, skipping fields no launcher reads."""
    from gld import input_pipeline

    return builder.as_data_source(split, decoders=input_pipeline.source_decoders())
