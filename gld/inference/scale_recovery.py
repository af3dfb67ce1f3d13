"""How well a trained workdir recovers metric depth on a dataset's test pairs
(`python -m experiments.predict --measure_scale`): `gld.inference.scale`'s measurements
run with the workdir's predictor, printed as a table and stored."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from tqdm import tqdm

from gld import input_pipeline
from gld.arguments import ArgumentError
from gld.inference import scale
from gld.inference.predict import DepthPredictor
from gld.runs import workdir as workdir_lib


def measure_workdir(
    workdir: str | Path,
    *,
    prepare_dataset: Callable[[str], Any],
    dataset: str | None = None,
    step: int | None = None,
    seed: int = 0,
    batch_size: int = 8,
    max_examples: int = 0,
    output_dir: str | Path | None = None,
    print_fn: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Measures the workdir's metric scale recovery on the test pairs of `dataset`.

    Args:
      workdir: a trained workdir.
      prepare_dataset: dataset name ('name/config') -> its built TFDS builder (the data
        layer's, which the library does not import).
      dataset: the dataset whose records hold true depth and pose (default: the
        workdir's); it needs train and test splits.
      step, seed, batch_size, max_examples: the checkpoint (default: latest), the seed of
        the range reading's pixel, pairs per model call, the first N test pairs (0 = all).
      output_dir: where scale_recovery.json and .md go (None: nowhere).
      print_fn: shows the dataset, the workdir and the table (`scale.scale_table`).

    Returns:
      What scale_recovery.json holds: dataset, workdir, seed and
      `scale.measure_scale_recovery`'s result.

    Raises:
      ArgumentError: the workdir has no stored config; the dataset lacks a split.
    """
    try:
        config = workdir_lib.load_run_config(workdir)
    except FileNotFoundError as error:
        raise ArgumentError(f"--workdir: {error}") from None
    builder = prepare_dataset(dataset or config.dataset)
    if "train" not in builder.info.splits or "test" not in builder.info.splits:
        raise ArgumentError(f"--dataset: {builder.info.full_name} needs train and test splits")
    decoders = input_pipeline.source_decoders()
    test_source = builder.as_data_source("test", decoders=decoders)
    train_source = builder.as_data_source("train", decoders=decoders)
    predictor = DepthPredictor.from_workdir(workdir, step=step)
    total = len(test_source) if max_examples <= 0 else max_examples
    with tqdm(total=min(total, len(test_source)), desc="scale", unit="pair") as bar:
        result = scale.measure_scale_recovery(
            lambda image1, image2, flow: predictor(image1, image2, flow),
            test_source,
            train_source,
            seed=seed,
            batch_size=batch_size,
            max_examples=max_examples,
            progress=lambda done: bar.update(done - bar.n),
        )
    table = scale.scale_table(result)
    print_fn(f"{builder.info.full_name}, workdir {workdir}\n{table}")
    stored = {"dataset": builder.info.full_name, "workdir": str(workdir), "seed": seed, **result}
    if output_dir:
        out_dir = Path(output_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / "scale_recovery.json").write_text(json.dumps(stored, indent=2) + "\n")
        (out_dir / "scale_recovery.md").write_text(table + "\n")
    return stored
