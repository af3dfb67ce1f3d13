"""Classical references on the online learner's own pairs (simulation only).

The offline evaluation shows every learned model beside the classical pipeline on the
same flow (`sfm_flow`); `StreamReferences` does the same on the robot's stream, with the
offline evaluation's own baselines (`gld.models.baselines.classical`, under their names
there). For each pair the learner predicts, after the prediction is published (its
latency is not touched), it predicts the frame's inverse depth

- "sfm_flow" (`SfMFlow`): the essential matrix from the pair's flow and triangulation, t
  at unit norm (the learner's units); a pair whose pose fails gets the running mean
  reference's constant, as the offline pipeline gets the training mean;
- "triangulation_gt_pose" (`TriangulationGtPose`): the same flow triangulated under the
  true relative pose, an oracle of what the flow itself says about depth (no learning
  can be asked to match it pair by pair, but a world whose flow gives it less gives
  every estimator less);

and the learner scores both against the same truth as its own prediction
(`OnlineLearner._score`): "abs_inv_<name>" in each logged row.
"""

from __future__ import annotations

import numpy as np

from gld.models.baselines.classical import SfMFlow, TriangulationGtPose

NAMES = ("sfm_flow", "triangulation_gt_pose")


class StreamReferences:
    """The classical predictions of one pair (module docstring)."""

    def __init__(self):
        # Failed pairs are replaced by the running reference (`predict` returns None).
        self._sfm = SfMFlow(fallback_inv_depth=1.0)
        self._gt_pose = TriangulationGtPose()

    def predict(
        self, example: dict[str, np.ndarray], true_rotation: np.ndarray, true_translation
    ) -> dict[str, np.ndarray | None]:
        """{name: [H, W] inverse depth in baselines, or None where the method failed}
        for the learner's pair `example` (flow frame -> partner, the two intrinsics) and
        the true relative pose frame -> partner."""
        batch = {key: example[key][None] for key in ("flow", "intrinsics1", "intrinsics2")}
        sfm = self._sfm.predict(batch)
        batch["rotation"] = np.asarray(true_rotation, np.float32)[None]
        batch["translation"] = np.asarray(true_translation, np.float32)[None]
        return {
            "sfm_flow": None if sfm["failed"][0] else np.asarray(sfm["inv_depth"][0]),
            "triangulation_gt_pose": np.asarray(self._gt_pose.predict(batch)["inv_depth"][0]),
        }
