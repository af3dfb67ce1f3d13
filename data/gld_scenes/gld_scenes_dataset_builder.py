"""`gld_scenes`: procedural two-view indoor scenes with exact geometry (TFDS builder).

Each example is a pair of views of a random room with boxes, spheres and
cylinders (drawn by `scenes.py`, ray cast by `raycast.py`, paired by `renderer.py`,
made a record by `example_records.py`; the configs are `scene_configs.py`'s),
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

Version 2.0.0 puts band-limited detail on every surface (`textures.SurfaceDetail`), so
that the estimated flow is right on the large plain, gradient and striped surfaces where
it used to be wrong; geometry, poses, depth and true flow are those of 1.0.0. The
`*_untextured` configs keep 1.0.0's look (the surfaces' textures alone), for analyses of
depth where the flow is wrong.

The dataset card (`metadata.json`) records, per split, the estimated flow's end-point
error, overall and by the texture kind of the surface (`flow_epe_by_texture_<split>`),
and the benchmark's signal (`signal_<split>`, see `dataset_card`): how far pixels
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
from collections.abc import Iterator
from typing import Any

import numpy as np
import tensorflow_datasets as tfds

import data
from gld import flow as flow_lib
from gld import records
from gld.runs import trained_flow

from . import dataset_card, example_records, scene_configs

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


class Builder(tfds.core.GeneratorBasedBuilder):
    """Procedural two-view scenes with exact depth, pose, intrinsics and flow."""

    VERSION = tfds.core.Version("2.0.0")
    RELEASE_NOTES = scene_configs.RELEASE_NOTES
    BUILDER_CONFIGS = scene_configs.all_configs()
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
            texture=dataset_card.texture_card(config.surface_detail),
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
            results = map(example_records.render_record, tasks)
            yield from self._collect(results, errors, valid_fractions, card)
        else:
            # Fork: workers inherit the imported modules (the builder may have been imported
            # from a path that a fresh interpreter could not import). A trained network's
            # flow (JAX, which must not be forked) is computed here, as the pairs come in.
            context = multiprocessing.get_context("fork")
            with context.Pool(self._workers) as pool:
                if flow_lib.is_learned(estimator):
                    tasks = [(self.builder_config, split, index) for index in range(count)]
                    pairs = pool.imap(example_records.render_pair_task, tasks, chunksize=4)
                    results = (
                        example_records.finish_record(
                            example_records.add_flow(pair, estimator), index
                        )
                        for index, pair in enumerate(pairs)
                    )
                else:
                    tasks = [
                        (self.builder_config, split, index, estimator) for index in range(count)
                    ]
                    results = pool.imap(example_records.render_record, tasks, chunksize=4)
                yield from self._collect(results, errors, valid_fractions, card)
        # The dataset card: written to metadata.json after the splits are generated.
        errors = np.asarray(errors, np.float64)
        finite = errors[np.isfinite(errors)]
        self.info.metadata[f"flow_epe_{split}"] = float(finite.mean()) if finite.size else None
        self.info.metadata[f"flow_epe_{split}_std"] = float(finite.std()) if finite.size else None
        self.info.metadata[f"gt_flow_valid_fraction_{split}"] = float(np.mean(valid_fractions))
        self.info.metadata[f"signal_{split}"] = dataset_card.summarise_signal(
            [signal for signal, _ in card], count
        )
        self.info.metadata[f"flow_epe_by_texture_{split}"] = dataset_card.summarise_texture_errors(
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
