"""`gld_scenes`: procedural two-view indoor scenes with exact geometry (TFDS builder).

Each example is a pair of views of a random room with boxes, spheres and
cylinders (drawn by `scenes.py`, ray cast by `raycast.py`, paired by `renderer.py`),
with both camera-z depth maps, both intrinsics, the relative pose, the exact flow
and its validity, and the flow estimated from the two images by an off-the-shelf
estimator (OpenCV DIS by default; `Builder(flow_estimator="flow_net:<workdir>")` stores a
trained flow network's instead). Records follow `gld.records`.

Build with `data.prepare("gld_scenes/small", data_dir)`, `python -m data.build
--dataset=gld_scenes/small` or `tfds.builder("gld_scenes/small").download_and_prepare()`
(array_record by default, no TensorFlow needed). Rendering can be spread over
processes: `data.prepare("gld_scenes/full", data_dir, workers=8)`. Example i of a
split is rendered from a generator seeded by (config seed, split, i), so the
records are identical across builds and independent of the number of workers.

Version 2.0.0 puts band-limited detail on every surface (`raycast.SurfaceDetail`), so
that the estimated flow is right on the large plain, gradient and striped surfaces where
it used to be wrong; geometry, poses, depth and true flow are those of 1.0.0. The
`*_untextured` configs keep 1.0.0's look (the surfaces' textures alone), for analyses of
depth where the flow is wrong.

The dataset card (`metadata.json`) records, per split, the estimated flow's end-point
error, overall and by the texture kind of the surface (`flow_epe_by_texture_<split>`),
and the benchmark's signal (`signal_<split>`, see `signal_statistics`): how far pixels
move, how much of that motion is parallax (the part that carries depth), how well
triangulation with the true pose recovers depth (and each pair's depth scale) from the
estimated and from the true flow, what the classical pipeline on the estimated flow
alone (`sfm_flow`: essential matrix, then triangulation) gets of the pose and the depth,
and the per-pair oracle constant's error; and what produced the stored flow
(`flow_estimator_source`).
"""

from __future__ import annotations

import dataclasses
import multiprocessing
from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

import data
from gld import flow as flow_lib
from gld import geometry, records
from gld.evaluation import metrics
from gld.models.baselines import classical
from gld.runs import trained_flow

from . import raycast, renderer, scenes

_DESCRIPTION = """\
Procedural two-view indoor scenes in the spirit of DeMoN's Scenes11: a room
(floor, walls, ceiling) with random boxes, spheres and cylinders, solid
procedural textures (plain colours, checkers, stripes, gradients, value noise)
with band-limited multi-octave detail fixed to every surface (the `*_untextured`
configs leave it out), ambient + Lambertian lighting (view independent). The
second view moves like a hand-held camera (rotation up to 10 degrees,
translation 0.05-0.5 m, flow up to about 40 px at 256x192). Exact depth of both
views, intrinsics, relative pose and ground-truth flow with validity (inside
view 2, not occluded); the stored `flow` is estimated from the images. The
`*_varying` configs perturb fx, fy, cx, cy of each view independently by up to
20%.
"""

_CITATION = """\
@article{loquercio2020learning,
  title={Learning Depth With Very Sparse Supervision},
  author={Loquercio, Antonio and Dosovitskiy, Alexey and Scaramuzza, Davide},
  journal={IEEE Robotics and Automation Letters},
  volume={5},
  number={4},
  pages={5542--5549},
  year={2020}
}
"""


# The card's signal statistics come from the first CARD_PAIRS pairs of each split (pairs
# are independent draws), so they cost seconds even for `full`.
CARD_PAIRS = 500
# The card's classical pipeline: `sfm_flow`'s pose estimate (numpy and OpenCV only, so it
# runs in the rendering workers); its fallback is never used here (a failed pair is
# counted, not scored).
_SFM_FLOW = classical.SfMFlow(fallback_inv_depth=1.0)


@dataclasses.dataclass(eq=False)
class SceneConfig(tfds.core.BuilderConfig):
    """A `gld_scenes` configuration.

    Attributes:
      height, width: image size in pixels.
      num_train, num_test: number of pairs per split.
      seed: seed of the whole dataset (with the split and the index).
      intrinsics_jitter: relative perturbation of each view's fx, fy, cx, cy (0 = nominal).
      surface_detail: detail on every surface (`scenes.SceneSettings.surface_detail`).
      flow_estimator: the stored estimated flow's estimator (`gld.flow.check_estimator`);
        a build may override it (`Builder(flow_estimator=...)`).
    """

    height: int = 192
    width: int = 256
    num_train: int = 40_000
    num_test: int = 1_000
    seed: int = 0
    intrinsics_jitter: float = 0.0
    surface_detail: bool = True
    flow_estimator: str = flow_lib.DEFAULT_ESTIMATOR

    def scene_settings(self) -> scenes.SceneSettings:
        return scenes.SceneSettings(
            height=self.height,
            width=self.width,
            intrinsics_jitter=self.intrinsics_jitter,
            surface_detail=self.surface_detail,
        )


_DETAIL_NOTE = (
    "Every surface carries band-limited multi-octave value noise fixed to it (object "
    "coordinates for objects, world coordinates for the room) that multiplies its albedo, "
    "each octave fading out between 4 and 2 pixels on the surface: the estimated flow is "
    "right where 1.0.0's large plain, gradient and striped surfaces left it wrong. "
    "Geometry, poses, depth and true flow are those of the previous version; the images "
    "and the estimated flow change. The *_untextured configs render the previous look."
)
RELEASE_NOTES = {"2.0.0": _DETAIL_NOTE, "1.0.0": "Initial release."}
# The varying configs' own history: their pairs changed when the intrinsics got a
# random stream of their own (the fixed configs' pairs did not).
VARYING_RELEASE = dict(
    version=tfds.core.Version("2.0.0"),
    release_notes={
        "2.0.0": _DETAIL_NOTE,
        "1.2.0": "Each pair is the fixed config's pair of the same index (scene, cameras' "
        "poses) with other intrinsics: the motion is bounded with the nominal intrinsics.",
        "1.1.0": "Each pair has the scene and the motion draws of the fixed config's pair "
        "of the same index.",
        "1.0.0": "Initial release.",
    },
)


def _configs() -> list[SceneConfig]:
    sizes = {
        "tiny": dict(height=48, width=64, num_train=32, num_test=16),
        "small": dict(height=96, width=128, num_train=2_000, num_test=200),
        "full": dict(height=192, width=256, num_train=40_000, num_test=1_000),
    }
    descriptions = {
        "tiny": "64x48, 32 train / 16 test pairs (tests).",
        "small": "128x96, 2,000 train / 200 test pairs (the default of the trainer).",
        "full": "256x192, 40,000 train / 1,000 test pairs (paper scale).",
    }
    configs = []
    for jitter, detail, suffix, extra in (
        (0.0, True, "", ""),
        (
            0.2,
            True,
            "_varying",
            " Varying intrinsics (20%); each pair is the fixed config's pair of the same "
            "index (scene, poses) seen with other intrinsics.",
        ),
        (
            0.0,
            False,
            "_untextured",
            " Without surface detail: the fixed config's pairs as version 1.0.0 rendered "
            "them (images and estimated flow alike), with large plain surfaces where the "
            "estimated flow is wrong.",
        ),
    ):
        for name, size in sizes.items():
            configs.append(
                SceneConfig(
                    name=name + suffix,
                    description=descriptions[name] + extra,
                    intrinsics_jitter=jitter,
                    surface_detail=detail,
                    **(VARYING_RELEASE if jitter else {}),
                    **size,
                )
            )
    return configs


def texture_card(surface_detail: bool) -> dict[str, Any]:
    """What the card says of the surfaces' texture: the kinds and, with surface detail,
    its settings (`raycast.SurfaceDetail`)."""
    card: dict[str, Any] = {"kinds": list(raycast.TEXTURES), "surface_detail": surface_detail}
    if surface_detail:
        card.update(
            detail_spacings_m=list(raycast.DETAIL_SPACINGS),
            detail_persistence=raycast.DETAIL_PERSISTENCE,
            detail_contrast=scenes.DETAIL_CONTRAST,
            detail_fade_pixels=list(raycast.DETAIL_FADE_PIXELS),
            note="value noise fixed to each surface multiplies its albedo by 1 + contrast * "
            "d (d in [-1, 1]); an octave of lattice spacing s fades out as s shrinks from "
            "the second to the first fade value in pixels on the surface",
        )
    return card


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


def signal_statistics(example: Mapping[str, Any]) -> dict[str, float]:
    """What one pair offers a depth learner: its motion, its parallax, its triangulability.

    Numpy only (it runs in the rendering workers). The triangulation is the
    `triangulation_gt_pose` baseline's (`classical.triangulate_batch`) and its Abs-Inv
    follows the evaluation's protocol, so the card's numbers are the ones
    `python -m experiments.evaluate --model=triangulation_gt_pose` reports.

    Args:
      example: a raw example or a stored record: 'depth1' [H, W]; 'flow' (the estimate)
        and 'gt_flow' [H, W, 2] pixels I1 -> I2; 'gt_flow_valid' [H, W] bool;
        'intrinsics1', 'intrinsics2' [4] normalised; 'rotation' [3, 3]; 'translation' [3].

    Returns:
      gt_flow_px_mean, gt_flow_px_median: |true flow| in pixels over its valid pixels;
      translational_flow_px_mean: |true flow - rotation-only flow| over the same pixels,
        where the rotation-only flow is the pair's flow with the translation set to zero
        (the flow at infinite depth), so the rest is the parallax that carries depth;
      triangulation_abs_inv_estimated_flow, triangulation_abs_inv_gt_flow: Abs-Inv of
        triangulation with the true pose from each flow, over every valid depth pixel,
        depth scaled so that ||t|| = 1;
      triangulation_scale_log_error_estimated_flow: log of the pair's median
        triangulated inverse depth (true pose, estimated flow) over its median true
        inverse depth: how well the estimated flow fixes the pair's depth scale even
        given the pose;
      oracle_constant_abs_inv: Abs-Inv of the pair's own median true inverse depth
        predicted everywhere (the per-pair oracle constant of the evaluations);
      sfm_flow_failed: 1 when the classical pipeline (`classical.SfMFlow`: essential
        matrix from the estimated flow) finds no pose, else 0;
      sfm_flow_rotation_deg, sfm_flow_translation_deg: its pose's rotation and
        translation-direction errors, and sfm_flow_abs_inv: Abs-Inv of triangulation
        with that pose (as the `sfm_flow` baseline predicts it); NaN when it failed
        (the evaluation then predicts the dataset mean).
      The flow values are NaN for a pair without a valid true-flow pixel.
    """
    depth = np.asarray(example["depth1"], np.float64)
    height, width = depth.shape
    intrinsics1 = np.asarray(example["intrinsics1"], np.float64)
    intrinsics2 = np.asarray(example["intrinsics2"], np.float64)
    rotation = np.asarray(example["rotation"], np.float64)
    translation = np.asarray(example["translation"], np.float64)
    gt_flow = np.asarray(example["gt_flow"], np.float64)
    flow_valid = np.asarray(example["gt_flow_valid"], bool)
    camera_matrix1 = geometry.intrinsics_matrix(intrinsics1, height, width)
    camera_matrix2 = geometry.intrinsics_matrix(intrinsics2, height, width)

    rotational_flow, _ = geometry.depth_to_flow(
        np.ones_like(depth), camera_matrix1, camera_matrix2, rotation, np.zeros(3)
    )
    magnitude = np.linalg.norm(gt_flow, axis=-1)[flow_valid]
    parallax = np.linalg.norm(gt_flow - rotational_flow, axis=-1)[flow_valid]

    sfm_rotation, sfm_translation, sfm_found = _SFM_FLOW.estimate_pose(
        np.asarray(example["flow"], np.float64), camera_matrix1, camera_matrix2
    )

    def thrice(value):
        return np.stack([np.asarray(value, np.float32)] * 3)

    # One batch of three: the estimated flow, then the true flow, with the true pose; the
    # estimated flow with sfm_flow's pose.
    predicted = classical.triangulate_batch(
        np.stack([example["flow"], example["gt_flow"], example["flow"]]).astype(np.float32),
        thrice(intrinsics1),
        thrice(intrinsics2),
        np.stack([rotation, rotation, sfm_rotation]).astype(np.float32),
        np.stack([translation, translation, sfm_translation]).astype(np.float32),
    )["inv_depth"]
    depth_valid = geometry.valid_depth(depth)
    true_inv_depth = np.linalg.norm(translation) / depth[depth_valid]
    abs_inv = [np.abs(true_inv_depth - pair[depth_valid]).mean() for pair in predicted]
    sfm_errors = metrics.pose_errors(sfm_rotation, sfm_translation, rotation, translation)
    nan = float("nan")
    true_median = np.median(true_inv_depth)
    scale_log_error = np.log(np.median(predicted[0][depth_valid]) / true_median)
    has_flow = bool(flow_valid.any())
    return {
        "gt_flow_px_mean": float(magnitude.mean()) if has_flow else nan,
        "gt_flow_px_median": float(np.median(magnitude)) if has_flow else nan,
        "translational_flow_px_mean": float(parallax.mean()) if has_flow else nan,
        "triangulation_abs_inv_estimated_flow": float(abs_inv[0]),
        "triangulation_abs_inv_gt_flow": float(abs_inv[1]),
        "triangulation_scale_log_error_estimated_flow": float(scale_log_error),
        "oracle_constant_abs_inv": float(np.abs(true_inv_depth - true_median).mean()),
        "sfm_flow_failed": float(not sfm_found),
        "sfm_flow_rotation_deg": float(sfm_errors["rotation_deg"]) if sfm_found else nan,
        "sfm_flow_translation_deg": float(sfm_errors["translation_deg"]) if sfm_found else nan,
        "sfm_flow_abs_inv": float(abs_inv[2]) if sfm_found else nan,
    }


def flow_error_by_texture(example: Mapping[str, Any]) -> dict[str, tuple[float, int]]:
    """The estimated flow's end-point error summed over the valid true-flow pixels of each
    texture kind of view 1's surface, and their count: {kind: (error sum px, pixels)}.

    Args:
      example: 'flow', 'gt_flow' [H, W, 2]; 'gt_flow_valid' [H, W] bool; 'texture_kind1'
        [H, W] int (an index into `raycast.TEXTURES`, as `renderer.render_pair` gives it).
    """
    valid = np.asarray(example["gt_flow_valid"], bool)
    error = np.linalg.norm(
        np.asarray(example["flow"], np.float64) - np.asarray(example["gt_flow"], np.float64),
        axis=-1,
    )
    kinds = np.asarray(example["texture_kind1"])
    return {
        kind: (float(error[valid & (kinds == index)].sum()), int((valid & (kinds == index)).sum()))
        for index, kind in enumerate(raycast.TEXTURES)
    }


def summarise_texture_errors(per_pair: list[dict[str, tuple[float, int]]]) -> dict[str, Any]:
    """The card's `flow_epe_by_texture_<split>` from `flow_error_by_texture` of some pairs:
    per texture kind, the mean end-point error over its pixels and its share of them."""
    total = sum(count for pair in per_pair for _, count in pair.values())
    summary: dict[str, Any] = {
        "pairs": len(per_pair),
        "note": "estimated flow's end-point error (px) over the valid true-flow pixels of "
        "each texture kind of view 1's surface (pixel-weighted), and the kind's share of "
        "those pixels",
    }
    for kind in raycast.TEXTURES:
        error_sum = sum(pair[kind][0] for pair in per_pair)
        count = sum(pair[kind][1] for pair in per_pair)
        summary[kind] = {
            "epe_px": error_sum / count if count else None,
            "pixel_share": count / total if total else None,
        }
    return summary


def summarise_signal(per_pair: list[dict[str, float]], split_pairs: int) -> dict[str, Any]:
    """The card's `signal_<split>` entry from `signal_statistics` of some of its pairs.

    Every value is the mean over pairs of the per-pair value, except gt_flow_px_median,
    the median over pairs of each pair's median; a log error also gets its standard
    deviation over pairs (`<name>_std`: the spread a per-pair scale keeps once a
    constant bias is removed). Pairs without a valid true-flow pixel are left out of
    the flow values.
    """
    summary: dict[str, Any] = {
        "pairs": len(per_pair),
        "split_pairs": split_pairs,
        "note": (
            f"over the first {len(per_pair)} of {split_pairs} pairs: means over pairs of "
            "per-pair values (gt_flow_px_median: the median of the pairs' medians); flow in "
            "pixels over valid true-flow pixels; translational = true flow minus the "
            "rotation-only flow (zero translation); triangulation with the true pose, "
            "Abs-Inv at ||t|| = 1 over valid depth pixels; scale log error: log(median "
            "triangulated / median true inverse depth), mean and std over pairs"
        ),
    }
    for name in per_pair[0] if per_pair else ():
        values = np.asarray([pair[name] for pair in per_pair], np.float64)
        values = values[np.isfinite(values)]
        reduce = np.median if name == "gt_flow_px_median" else np.mean
        summary[name] = float(reduce(values)) if values.size else None
        if "log_error" in name:
            summary[f"{name}_std"] = float(values.std()) if values.size else None
    return summary


_CardEntry = tuple[dict[str, float], dict[str, tuple[float, int]]]


def _render_record(
    task: tuple[SceneConfig, str, int, str],
) -> tuple[str, dict[str, Any], float, float, _CardEntry | None]:
    """Pool worker (or this process): `render_example` with the record already encoded
    (PNG in parallel), and for the first CARD_PAIRS of a split the stored record's
    `signal_statistics` and `flow_error_by_texture`."""
    return _finish_record(render_example(*task), task[2])


def _finish_record(
    rendered: tuple[str, dict[str, Any], float, float], index: int
) -> tuple[str, dict[str, Any], float, float, _CardEntry | None]:
    example_id, example, epe, valid_fraction = rendered
    record = records.encode(example)
    card = None
    if index < CARD_PAIRS:
        card = (
            signal_statistics(record),
            flow_error_by_texture({**record, "texture_kind1": example["texture_kind1"]}),
        )
    return example_id, record, epe, valid_fraction, card


def _render_pair_task(task: tuple[SceneConfig, str, int]) -> dict[str, Any]:
    return render_pair(*task)


class Builder(tfds.core.GeneratorBasedBuilder):
    """Procedural two-view scenes with exact depth, pose, intrinsics and flow."""

    VERSION = tfds.core.Version("2.0.0")
    RELEASE_NOTES = RELEASE_NOTES
    BUILDER_CONFIGS = _configs()
    DEFAULT_CONFIG_NAME = "small"

    def __init__(
        self,
        *,
        workers: int = 1,
        flow_estimator: str | None = None,
        file_format: str | None = None,
        **kwargs,
    ):
        """Args: workers: processes rendering in parallel (1 renders in this process);
        the records do not depend on it. flow_estimator: the stored flow's estimator
        (`gld.flow.check_estimator`; None: the config's); a trained flow network runs in
        this process, after the workers have rendered. file_format: None is
        `data.FILE_FORMAT`. Other arguments go to TFDS."""
        if workers < 1:
            raise ValueError(f"workers must be >= 1, got {workers}")
        if flow_estimator is not None:
            flow_lib.check_estimator(flow_estimator)
        self._workers = int(workers)
        self._flow_estimator = flow_estimator
        super().__init__(file_format=file_format or data.FILE_FORMAT, **kwargs)

    @property
    def flow_estimator(self) -> str:
        """The stored flow's estimator: the build's override or the config's."""
        return self._flow_estimator or self.builder_config.flow_estimator

    def build_options(self, split: str) -> dict[str, Any]:
        """The options that shape the records of `split` (stored in the metadata)."""
        del split  # every split is built alike
        return {"flow_estimator": self.flow_estimator}

    def _info(self) -> tfds.core.DatasetInfo:
        config = self.builder_config
        settings = config.scene_settings()
        metadata = tfds.core.MetadataDict(
            generator=dataclasses.asdict(settings),
            seed=config.seed,
            num_train=config.num_train,
            num_test=config.num_test,
            flow_estimator=self.flow_estimator,
            texture=texture_card(config.surface_detail),
        )
        return self.dataset_info_from_configs(
            description=_DESCRIPTION,
            features=records.features(config.height, config.width),
            homepage="https://github.com/uzh-rpg/learning_depth_with_very_sparse_supervision",
            citation=_CITATION,
            metadata=metadata,
        )

    def _split_generators(self, dl_manager: tfds.download.DownloadManager):
        del dl_manager  # everything is rendered
        return {
            "train": self._generate_examples("train", self.builder_config.num_train),
            "test": self._generate_examples("test", self.builder_config.num_test),
        }

    def _generate_examples(self, split: str, count: int) -> Iterator[tuple[str, dict[str, Any]]]:
        estimator = self.flow_estimator
        errors, valid_fractions, card = [], [], []
        if self._workers == 1:
            tasks = [(self.builder_config, split, index, estimator) for index in range(count)]
            results = map(_render_record, tasks)
            yield from self._collect(results, errors, valid_fractions, card)
        else:
            # Fork: workers inherit the imported modules (the builder may have been imported
            # from a path that a fresh interpreter could not import). A trained network's
            # flow (JAX, which must not be forked) is computed here, as the pairs come in.
            context = multiprocessing.get_context("fork")
            with context.Pool(self._workers) as pool:
                if flow_lib.is_learned(estimator):
                    tasks = [(self.builder_config, split, index) for index in range(count)]
                    pairs = pool.imap(_render_pair_task, tasks, chunksize=4)
                    results = (
                        _finish_record(add_flow(pair, estimator), index)
                        for index, pair in enumerate(pairs)
                    )
                else:
                    tasks = [
                        (self.builder_config, split, index, estimator) for index in range(count)
                    ]
                    results = pool.imap(_render_record, tasks, chunksize=4)
                yield from self._collect(results, errors, valid_fractions, card)
        # The dataset card: written to metadata.json after the splits are generated.
        errors = np.asarray(errors, np.float64)
        finite = errors[np.isfinite(errors)]
        self.info.metadata[f"flow_epe_{split}"] = float(finite.mean()) if finite.size else None
        self.info.metadata[f"flow_epe_{split}_std"] = float(finite.std()) if finite.size else None
        self.info.metadata[f"gt_flow_valid_fraction_{split}"] = float(np.mean(valid_fractions))
        self.info.metadata[f"signal_{split}"] = summarise_signal(
            [signal for signal, _ in card], count
        )
        self.info.metadata[f"flow_epe_by_texture_{split}"] = summarise_texture_errors(
            [texture_errors for _, texture_errors in card]
        )
        self.info.metadata.setdefault("build_options", {})[split] = self.build_options(split)
        self.info.metadata["flow_estimator_source"] = trained_flow.describe_flow(estimator)

    @staticmethod
    def _collect(results, errors: list, valid_fractions: list, card: list):
        for example_id, record, epe, valid_fraction, card_entry in results:
            errors.append(epe)
            valid_fractions.append(valid_fraction)
            if card_entry is not None:
                card.append(card_entry)
            yield example_id, record
