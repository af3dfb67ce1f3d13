"""Input pipeline: a random-access record source (e.g. a TFDS data source) -> grain batches.

Training (`train_dataset`): per-process shard (`process_index::process_count`) ->
seeded shuffle, reshuffled every epoch -> decode -> augmentation (rotate 180 degrees
with p = 0.5, then mirror along x with p = 0.5) -> scale normalisation (||t|| = 1) ->
sparse sampling of the supervised pixels -> batches of the per-process batch size,
the examples optionally prepared by grain worker processes. The dataset is infinite
and its iterator state (the next batch's number) is JSON-serialisable, so a trainer can
checkpoint it and resume with any worker count.

Evaluation (`eval_batches`): one pass over the process's shard, no augmentation,
dense supervision mask, the last batch padded with masked-out copies.

Each example is made by `gld.contract.prepare_example` (decoding, augmentation, scale,
sparse pixels, with randomness seeded per example), so an example gets the same
treatment whatever the shard, shuffle or worker count.
"""

from __future__ import annotations

import math
import os
import threading
import time
import warnings
from collections.abc import Iterator, Sequence
from typing import Any

import grain
import numpy as np

from gld import records
from gld.contract import (
    FLOW_SOURCES,
    UNUSED_RECORD_KEYS,
    needed_fields,
    prepare_example,
    stored_fields,
)

# Threads preparing examples in each process. grain's defaults (16 threads, 500
# prefetched elements) suit small remote records; ours are large decoded images, and
# a 500-example buffer would cost ~1 GB and seconds before the first batch.
_READ_THREADS = 2
_PREFETCH_BATCHES = 2


# ---------------------------------------------------------------------------- reading


def source_decoders() -> dict[str, Any]:
    """TFDS decoders that skip record fields the pipeline never reads (view-2 depth).

    Decompressing `depth2` costs about a sixth of an example's CPU time; pass these to
    `builder.as_data_source(split, decoders=source_decoders())`.
    """
    import tensorflow_datasets as tfds

    return {key: tfds.decode.SkipDecoding() for key in UNUSED_RECORD_KEYS}


# Training reads every record once an epoch. The records a process read are kept, decoded
# (`records.decode`), up to this many bytes per process (grain worker or trainer): TFDS's
# deserialising and zlib and the images' PNG decoding are most of an example's
# preparation, CPU time the train step would otherwise share its cores with (on
# gld_scenes/small, whose 2,000 decoded records take ~760 MB, the pipeline's 42-52 ms of
# CPU a batch become 20-27). Records beyond the budget are read again every epoch.
_RECORD_CACHE_BYTES = 1 << 30


def _record_bytes(record: dict[str, Any]) -> int:
    return sum(getattr(value, "nbytes", None) or len(value) for value in record.values())


def _read_only(record: dict[str, Any]) -> dict[str, Any]:
    """The record with its arrays read-only: a kept record is shared by every epoch, so
    a writer would change the next epoch's example; this way it raises instead."""
    for value in record.values():
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
    return record


class _RecordReader:
    """Reads records by index and names each by file and index for error messages.

    With `cache_bytes`, every record read is decoded (`records.decode`: images out of
    PNG, arrays in their decoded dtypes) and kept so (read-only) until the kept ones take
    that many bytes; beyond it, records are read and decoded again at every use: the
    same examples either way (`decodes` says that `read` returns them decoded).
    Picklable as long as the source is; a grain worker's copy keeps nothing yet (the
    budget is each process's).
    """

    def __init__(self, source: Sequence[Any], cache_bytes: int = 0):
        self.source = source
        self.cache_bytes = cache_bytes
        self.decodes = cache_bytes > 0
        self._cache: dict[int, dict[str, Any]] = {}
        self._cached_bytes = 0
        self._files: list[tuple[int, str, int]] = []  # (first index, file name, skip)
        self._describe_files()

    def __getstate__(self) -> dict[str, Any]:
        # A worker gets the source, not what this process kept.
        return {**self.__dict__, "_cache": {}, "_cached_bytes": 0}

    def _describe_files(self) -> None:
        """Collects the source's files when it is a TFDS data source (others: index only)."""
        try:
            info = self.source.dataset_info
            instructions = info.splits[self.source.split].file_instructions
        except Exception:  # any source without TFDS metadata
            return
        first = 0
        for instruction in instructions:
            take = instruction.take
            if take is None or take < 0:
                take = instruction.examples_in_shard - instruction.skip
            self._files.append((first, str(instruction.filename), instruction.skip))
            first += take

    def where(self, index: int) -> str:
        """'file <name>, record <i> (index <j> of <source>)' or 'record <j> of <source>'."""
        name = getattr(self.source, "split", None) or type(self.source).__name__
        for first, filename, skip in reversed(self._files):
            if index >= first:
                return f"file {filename}, record {index - first + skip} (index {index} of {name})"
        return f"record {index} of {name}"

    def read(self, index: int) -> tuple[dict[str, Any], str]:
        where = self.where(index)
        record = self._cache.get(index)
        if record is not None:
            return record, where
        try:
            record = self.source[index]
        except Exception as error:  # TFDS and array_record raise many kinds
            raise ValueError(f"{where}: cannot read the record ({error})") from error
        if self.decodes:
            record = records.decode(record, where=where)
            size = _record_bytes(record)
            # Two reader threads adding at once may overshoot the budget by a record.
            if self._cached_bytes + size <= self.cache_bytes:
                self._cache[index] = _read_only(record)
                self._cached_bytes += size
        return record, where


class _FirstRecords:
    def __init__(self, source: Sequence[Any], count: int):
        self.source, self.count = source, min(count, len(source))

    def __len__(self) -> int:
        return self.count

    def __getitem__(self, index: int):
        if not 0 <= index < self.count:
            raise IndexError(index)
        return self.source[index]


def first_records(source: Sequence[Any], count: int) -> Sequence[Any]:
    """The first `count` records of a random-access source (all of them when 0)."""
    return _FirstRecords(source, count) if count else source


def _check_sharding(num_examples: int, process_index: int, process_count: int) -> None:
    if process_count < 1 or not 0 <= process_index < process_count:
        raise ValueError(
            f"process_index {process_index} is not in [0, process_count={process_count})"
        )
    if num_examples == 0:
        raise ValueError("the data source is empty")


def _shard_indices(num_examples: int, process_index: int, process_count: int) -> grain.MapDataset:
    """This process's record indices: process_index, process_index + process_count, ..."""
    return grain.MapDataset.range(num_examples)[process_index::process_count]


def _enable_grain_workers() -> None:
    """grain 0.2 reads its absl flags in worker start-up; give it their defaults.

    grain keeps its configuration only in absl flags, so this is the one place the
    library touches them: without it a worker of a program that never parsed flags dies
    with UnparsedFlagAccessError (--grain_enable_multiprocess_worker_profiling). A
    launcher that parsed flags (absl.app.run) is unaffected.
    """
    from absl import flags

    if not flags.FLAGS.is_parsed():
        flags.FLAGS.mark_as_parsed()


class ExitWithParent:
    """A grain `worker_init_fn`: the worker exits within `period` seconds of its
    parent's death.

    A training process killed with SIGKILL runs no clean-up, and grain's workers would
    live on (~250 MB each). The parent's pid is taken where the workers are started and
    handed to them: a worker that reads its parent itself, after the parent already
    died, would watch the process that adopted it and live on. A worker whose parent
    is already gone when it starts exits at once.
    """

    def __init__(self, parent: int | None = None, period: float = 1.0):
        self.parent = os.getpid() if parent is None else parent
        self.period = period

    def __call__(self, worker_index: int = 0, worker_count: int = 0) -> None:
        del worker_index, worker_count
        if os.getppid() != self.parent:
            os._exit(1)

        def watch() -> None:
            while os.getppid() == self.parent:
                time.sleep(self.period)
            os._exit(1)

        threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


class _PrepareTrainExample:
    """The training map (index in the repeated shard, record index) -> example.

    A class rather than a closure so that grain can pickle it into worker processes.
    """

    def __init__(self, reader: _RecordReader, shard_size: int, **options: Any):
        self.reader = reader
        self.shard_size = shard_size
        self.options = options

    def __call__(self, position: int, record_index: int) -> dict[str, Any]:
        record, where = self.reader.read(int(record_index))
        epoch = position // self.shard_size
        return prepare_example(
            record, epoch=epoch, where=where, decoded=self.reader.decodes, **self.options
        )


def train_dataset(
    source: Sequence[Any],
    *,
    batch_size: int,
    seed: int,
    gt_pixels: int,
    flow_source: str = "estimated",
    augment: bool = True,
    fixed_sparse_pixels: bool = False,
    worker_count: int = 0,
    keys: Sequence[str] | None = None,
    process_index: int = 0,
    process_count: int = 1,
) -> grain.IterDataset:
    """The infinite training stream of this process.

    Args:
      source: random-access records (`len`, `__getitem__`), e.g.
        `builder.as_data_source("train")`.
      batch_size: examples per batch of THIS process (global batch // process_count).
      seed: data seed in [0, 2**32): shuffle, augmentation and sparse sampling.
      gt_pixels: supervised pixels per example (1, 4, 16, 64, ...; 0 = dense).
      flow_source: "estimated" or "gt" flow as the network's input.
      augment: rotate-180 / mirror-x augmentation.
      fixed_sparse_pixels: the same supervised pixels in every epoch.
      worker_count: grain worker processes (0 = in the calling process). The batches
        are the same for every worker count.
      keys: the fields the consumer reads (e.g. `gld.training.trainer.TRAIN_KEYS`); the others are
        not augmented or batched. None keeps the whole contract.
      process_index, process_count: this process's shard is records
        `process_index::process_count`; the shards are disjoint and cover the split.

    Returns:
      a grain IterDataset of batches: the example dicts with a leading [batch_size] axis
      (numpy arrays; "id" an array of str). `iter()` gives a `TrainBatches` whose
      `get_state()` is JSON-serialisable and whose `set_state()` resumes the same
      batches, with any worker count.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if not 0 <= seed < 2**32:
        raise ValueError(f"seed must be in [0, 2**32), got {seed}")
    if gt_pixels < 0:
        raise ValueError(f"gt_pixels must be >= 0 (0 = dense), got {gt_pixels}")
    if flow_source not in FLOW_SOURCES:
        raise ValueError(f"unknown flow_source {flow_source!r}; valid: {FLOW_SOURCES}")
    if worker_count < 0:
        raise ValueError(f"worker_count must be >= 0, got {worker_count}")
    _check_sharding(len(source), process_index, process_count)

    shard = _shard_indices(len(source), process_index, process_count)
    if len(shard) == 0:
        raise ValueError(
            f"process {process_index} of {process_count} gets no records of a source "
            f"with {len(source)}"
        )
    prepare = _PrepareTrainExample(
        _RecordReader(source, cache_bytes=_RECORD_CACHE_BYTES),
        len(shard),
        seed=seed,
        gt_pixels=gt_pixels,
        flow_source=flow_source,
        augment=augment,
        fixed_sparse_pixels=fixed_sparse_pixels,
        keys=keys,
    )
    # Shuffle then repeat: grain reshuffles with shuffle_seed + epoch in every epoch. The
    # seed is scrambled so that run seeds s and s + 1 do not share shifted permutations.
    shuffle_seed = int(np.random.SeedSequence(seed).generate_state(1)[0])
    examples = shard.shuffle(seed=shuffle_seed).repeat(None).map_with_index(prepare)
    return _TrainStream(examples, batch_size, worker_count)


class _TrainStream(grain.IterDataset):
    """The training batches: `iter()` gives a `TrainBatches` from the first batch."""

    def __init__(self, examples: grain.MapDataset, batch_size: int, worker_count: int):
        super().__init__()
        self._examples, self._batch_size, self._worker_count = examples, batch_size, worker_count

    def __iter__(self) -> TrainBatches:
        return TrainBatches(self._examples, self._batch_size, self._worker_count)

    def __str__(self) -> str:
        return f"TrainStream(batch_size={self._batch_size}, worker_count={self._worker_count})"


class TrainBatches(grain.DatasetIterator):
    """Batch k holds examples k * batch_size ... (k + 1) * batch_size - 1 of the stream,
    whichever process prepares them.

    Its state is the next batch's number, `{"next_batch": k}`: a checkpoint made with
    one worker count resumes with any other, on the same batches. The workers each
    prepare every `worker_count`-th example and grain interleaves them back in order;
    the batches are put together here.
    """

    def __init__(self, examples: grain.MapDataset, batch_size: int, worker_count: int):
        super().__init__()
        self._examples, self._batch_size, self._worker_count = examples, batch_size, worker_count
        self._next_batch = 0
        self._batches: Iterator[dict[str, Any]] | None = None

    def _open(self) -> Iterator[dict[str, Any]]:
        if self._batches is None:
            start = self._next_batch * self._batch_size
            dataset = self._examples[start:].to_iter_dataset(
                grain.ReadOptions(
                    num_threads=_READ_THREADS,
                    prefetch_buffer_size=_PREFETCH_BATCHES * self._batch_size,
                )
            )
            if self._worker_count > 0:
                _enable_grain_workers()
                dataset = dataset.mp_prefetch(
                    grain.MultiprocessingOptions(num_workers=self._worker_count),
                    worker_init_fn=ExitWithParent(),
                )
            self._batches = iter(dataset.batch(self._batch_size, drop_remainder=True))
        return self._batches

    def __next__(self) -> dict[str, Any]:
        batch = next(self._open())
        self._next_batch += 1
        return batch

    def get_state(self) -> dict[str, Any]:
        return {"next_batch": self._next_batch}

    def set_state(self, state: dict[str, Any]) -> None:
        next_batch = _next_batch(state, self._batch_size)
        self.close()
        self._next_batch = next_batch

    def start_prefetch(self) -> None:
        self._open()

    def close(self) -> None:
        if self._batches is not None:
            close = getattr(self._batches, "close", None)
            if close is not None:
                close()
            self._batches = None


def _next_batch(state: dict[str, Any], batch_size: int) -> int:
    """The next batch's number from a state of `TrainBatches` or of the grain iterators
    that checkpoints of earlier versions hold."""
    if "next_batch" in state:
        next_batch = state["next_batch"]
    elif "next_index" in state:  # one process's examples, batched in order
        next_batch, rest = divmod(state["next_index"], batch_size)
        if rest:
            raise ValueError(
                f"the data state {state} is not at a batch boundary of batch size {batch_size}"
            )
    elif "iterators_in_use_states" in state:
        # Worker processes that each batched their own share: the batches read are
        # counted, but the examples in them were not the consecutive ones read now.
        examples = sum(part["next_index"] for part in state["iterators_in_use_states"])
        next_batch = examples // batch_size
        warnings.warn(
            f"the data state was saved with {len(state['iterators_in_use_states'])} "
            f"workers by an earlier version; training goes on from batch {next_batch} of "
            "the stream every worker count now reads, so a few examples of the current "
            "epoch are seen again or skipped",
            stacklevel=3,
        )
    else:
        raise ValueError(f"not a training data state: {state}")
    if not isinstance(next_batch, int) or next_batch < 0:
        raise ValueError(f"not a training data state: {state}")
    return next_batch


# ------------------------------------------------------------------------- evaluation


def num_eval_batches(num_examples: int, batch_size: int, process_count: int = 1) -> int:
    """Batches every process yields in one evaluation pass (the largest shard decides)."""
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    largest_shard = math.ceil(num_examples / process_count)
    return math.ceil(largest_shard / batch_size)


class _PrepareEvalExample:
    """(record index, is real) -> unaugmented example with dense mask and example_mask."""

    def __init__(self, reader: _RecordReader, flow_source: str, keys: Sequence[str] | None):
        self.reader = reader
        self.flow_source = flow_source
        self.keys = keys

    def __call__(self, entry: tuple[int, bool]) -> dict[str, Any]:
        record_index, is_real = entry
        record, where = self.reader.read(int(record_index))
        example = prepare_example(
            record,
            epoch=0,
            seed=0,
            gt_pixels=0,
            flow_source=self.flow_source,
            augment=False,
            keys=self.keys,
            where=where,
        )
        example["example_mask"] = np.bool_(is_real)
        return example


def eval_batches(
    source: Sequence[Any],
    *,
    batch_size: int,
    flow_source: str = "estimated",
    keys: Sequence[str] | None = None,
    process_index: int = 0,
    process_count: int = 1,
) -> Iterator[dict[str, Any]]:
    """One pass over this process's shard: no augmentation, dense `sparse_mask`.

    Every batch has `batch_size` rows and an `example_mask` [B] bool; the last batch is
    padded with copies of a real example (mask False), and every process yields
    `num_eval_batches(len(source), batch_size, process_count)` batches, so collective
    evaluation steps stay in lockstep.

    Yields:
      batch dicts of the example contract (only `keys` and "id", when given) plus
      `example_mask`.
    """
    if flow_source not in FLOW_SOURCES:
        raise ValueError(f"unknown flow_source {flow_source!r}; valid: {FLOW_SOURCES}")
    _check_sharding(len(source), process_index, process_count)
    # example_mask is made here, not by `prepare_example`.
    example_keys = None if keys is None else tuple(k for k in keys if k != "example_mask")
    if example_keys is not None:
        source = records.decoding_only(
            source, stored_fields(needed_fields(example_keys), flow_source)
        )
    num_batches = num_eval_batches(len(source), batch_size, process_count)
    shard = list(range(len(source))[process_index::process_count])
    # A process whose shard is empty still pads with a real example (the split's first).
    padding_index = shard[0] if shard else 0
    entries = [(index, True) for index in shard]
    entries += [(padding_index, False)] * (num_batches * batch_size - len(entries))
    dataset = (
        grain.MapDataset.source(entries)
        .map(_PrepareEvalExample(_RecordReader(source), flow_source, example_keys))
        .batch(batch_size)
    )
    yield from dataset
