"""One example of a `gld_scenes` config as a record: rendered, its flow estimated, encoded.

An example is a pure function of (config, split, index) (`renderer.example_rng`).
`render_example` renders it and estimates its flow; `render_record` (a worker of the
builder's pool) also encodes it and, for the first `dataset_card.CARD_PAIRS` pairs of a
split, computes its part of the dataset card. With a trained flow network, which must
not run in a forked worker, the workers render (`render_pair_task`) and the builder's
process adds the flow (`add_flow`, `finish_record`).
"""

from __future__ import annotations

from typing import Any

from gld import flow as flow_lib
from gld import records
from gld.runs import trained_flow

from . import dataset_card, renderer
from .scene_configs import SceneConfig


def render_example(
    config: SceneConfig, split: str, index: int, flow_estimator: str | None = None
) -> tuple[str, dict[str, Any], float, float]:
    """Renders example `index` of `split` (a raw record, see `gld.records`).

    Args:
      flow_estimator: the stored flow's estimator; None is the config's.

    Returns:
      The example id, the example (numpy, before `records.encode`), the end-point
      error (pixels) of the estimated flow against the true flow on valid pixels,
      and the fraction of valid true-flow pixels.
    """
    return add_flow(render_pair(config, split, index), flow_estimator or config.flow_estimator)


def render_pair(config: SceneConfig, split: str, index: int) -> dict[str, Any]:
    """Example `index` of `split` without its estimated flow (numpy only: safe in a
    forked worker), with its "id" (and view 1's "texture_kind1", which is not stored)."""
    example = renderer.render_pair(
        renderer.example_rng(config.seed, split, index), config.scene_settings()
    )
    example["id"] = f"gld_scenes/{config.name}/{split}/{index:05d}"
    return example


def add_flow(
    example: dict[str, Any], flow_estimator: str
) -> tuple[str, dict[str, Any], float, float]:
    """`render_example`'s result from a `render_pair` example: its estimated flow added."""
    example["flow"] = trained_flow.estimate_flow(
        example["image1"], example["image2"], method=flow_estimator
    )
    epe = flow_lib.endpoint_error(example["flow"], example["gt_flow"], example["gt_flow_valid"])
    return example["id"], example, epe, float(example["gt_flow_valid"].mean())


_CardEntry = tuple[dict[str, float], dict[str, tuple[float, int]]]


def render_record(
    task: tuple[SceneConfig, str, int, str],
) -> tuple[str, dict[str, Any], float, float, _CardEntry | None]:
    """Pool worker (or this process): `render_example` with the record already encoded
    (PNG in parallel), and for the first `dataset_card.CARD_PAIRS` of a split the stored
    record's `dataset_card.signal_statistics` and `dataset_card.flow_error_by_texture`."""
    return finish_record(render_example(*task), task[2])


def finish_record(
    rendered: tuple[str, dict[str, Any], float, float], index: int
) -> tuple[str, dict[str, Any], float, float, _CardEntry | None]:
    """`render_record`'s result from a `render_example` result of example `index`."""
    example_id, example, epe, valid_fraction = rendered
    record = records.encode(example)
    card = None
    if index < dataset_card.CARD_PAIRS:
        card = (
            dataset_card.signal_statistics(record),
            dataset_card.flow_error_by_texture(
                {**record, "texture_kind1": example["texture_kind1"]}
            ),
        )
    return example_id, record, epe, valid_fraction, card


def render_pair_task(task: tuple[SceneConfig, str, int]) -> dict[str, Any]:
    """Pool worker: `render_pair` of a (config, split, index) task."""
    return render_pair(*task)
