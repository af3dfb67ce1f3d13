r"""Converts a robot's recording into a DeMoN-format HDF5 file for the `demon/custom` config.

    python -m data.demon.convert --images=rec/rgb --poses=rec/groundtruth.txt \
        --intrinsics=517.3,516.5,318.6,255.3 --depth=rec/range.csv \
        --output_dir=~/demon --test_fraction=0.2

then `python -m experiments.train --dataset=demon/custom --manual_dir=~/demon`.

Inputs
* `--images`: a folder of images (PNG, JPEG, ...), in name order = time order.
* `--poses`: `--pose_format=tum`: the TUM trajectory format, one line
  `timestamp tx ty tz qx qy qz qw` per pose, camera-to-world (the camera's position
  and orientation in the world, as TUM defines it), matched to the images as
  `--match_frames` says (below). `--pose_format=matrix`: a `.npy` [N, 4, 4] or a
  text file with one row-major 4x4 per line (16 numbers, or 17 with a leading
  timestamp, which is not read), in the i-th-image order;
  `--pose_direction` says whether they map camera to world (default, what SLAM
  systems export) or world to camera (`X_cam = R X_world + t`, DeMoN's convention).
* `--intrinsics`: `fx,fy,cx,cy` in pixels, or a file with those 4 numbers or a 3x3 K
  (skew is dropped), in OpenCV's convention: pixel (0, 0) has its centre at (0, 0).
  (DeMoN stores the principal point with the origin at the top-left corner; the
  converter adds the half pixel.)
* `--depth` (`--depth_scale` metres per stored unit, `--depth_metric` camera_z or
  ray_length): a folder of dense depth images named like the images (16-bit PNG,
  0 = no reading, e.g. TUM's with scale 0.0002) or `.npy` arrays; or a CSV
  `frame,u,v,depth` of sparse range readings (a single-pixel range sensor: every
  other pixel is invalid), `frame` being the image's name without extension or its
  index in name order (see `--match_frames`), `u, v` pixel coordinates in the image
  (rounded). A range sensor measures along its beam: pass `--depth_metric=ray_length`
  if it does.

Matching frames (`--match_frames`; the same flag as `python -m experiments.predict`'s):
* `auto` (default): a depth image of the image's name, a reading whose `frame` is the
  image's name or index; otherwise (poses always) the nearest time stamp within
  `--max_time_difference` seconds when the images are named by one (TUM's
  `1305031102.175304.png`) and the TUM poses or the depth images have stamps; else the
  order.
* `time`: the nearest time stamp, as above, for poses, depth images and readings (their
  `frame` a time stamp); refused, naming the file, when a name is not one.
* `order`: the i-th image gets the i-th pose, depth image, and frame of the readings (in
  the order the CSV first names them); refused when their counts differ. For images
  numbered by frame (`000000.png`) beside a timestamped trajectory.
A name is a time stamp only when it is a plain decimal number (digits, at most one '.';
not `07_1`, `-1`, `1e5`, `nan`). Images that look numbered by frame (whole numbers
seconds away from every stamp) are refused with the hint to use `order`.

Pairs: frame i with frame i + `--frame_gap`; with `--min_baseline` / `--max_baseline`
(metres) instead frame i with the nearest later frame (at most `--max_frame_gap`
ahead) whose camera centre lies in that distance range. A pair (i, j) is frame i's
depth: training supervises it with frame i's readings, as the predictor scales it by
them. It is written only when frame i has a depth reading, and frame j too (the
`demon/custom` reader refuses a view without depth); the pairs left out are counted by
the frame without (`no_reading_on_first_frame`, `no_reading_on_second_frame`).

Output: `<output_dir>/custom_<split>.h5` (`custom_<split>_<recording>.h5` with
`--recording`), one scene group per pair (`<frame1>__<frame2>`, two views,
`viewpoint_pairs = [0 1]`), so the builder's train and test splits see every pair.
`--test_fraction` holds out the last frames of the recording as the test split
(pairs across the boundary are dropped, so no test frame is seen in training).
Images are WebP (lossless by default), depth float16 LZ4 blocks.

All or nothing: the files are written under temporary names in `--output_dir` and
renamed into place only when every split asked for has at least one pair; a run that
fails or finds no pair writes nothing (and exits non-zero). An existing output file
is replaced only with `--overwrite`, and re-converting a recording replaces all of its
files: the same recording's file of the split not written now (from an earlier run with
`--test_fraction` or the other `--split`) is removed with `--overwrite` and refused
without it, since its pairs would be in both splits. Every number read is checked (finite poses that
are rotations, intrinsics with fx, fy > 0 and the principal point inside the image,
range readings finite and > 0 inside the image, depth images without negative values;
0, NaN and inf in a depth image mean "no reading"), and an error names the file and
line. `--recording` is a plain name (letters, digits, '_', '-', '.').

This module is the command line only: `recordings` reads the inputs and
`writer.write_recording` pairs, splits and writes them.
"""

from __future__ import annotations

from collections.abc import Sequence

from absl import flags

from data import command_line
from data.demon import recordings, writer
from gld.arguments import ArgumentError

flags.DEFINE_string("images", None, "Folder of images, in name order.", required=True)
flags.DEFINE_string("poses", None, "Trajectory file (see --pose_format).", required=True)
flags.DEFINE_string("intrinsics", None, "fx,fy,cx,cy in pixels, or a file.", required=True)
flags.DEFINE_string(
    "depth",
    None,
    "Folder of depth images, or frame,u,v,depth CSV. A pair (i, j) is written when both "
    "frames have a reading; frame i's is the pair's depth.",
    required=True,
)
flags.DEFINE_string("output_dir", None, "Where custom_<split>.h5 go.", required=True)
flags.DEFINE_enum("pose_format", "tum", recordings.POSE_FORMATS, "TUM lines or 4x4 matrices.")
flags.DEFINE_enum(
    "pose_direction",
    "camera_to_world",
    recordings.POSE_DIRECTIONS,
    "What --pose_format=matrix poses map.",
)
flags.DEFINE_float("depth_scale", 1.0, "Metres per stored depth unit (TUM PNG: 0.0002).")
flags.DEFINE_enum(
    "depth_metric", "camera_z", recordings.DEPTH_METRICS, "z, or distance along the ray."
)
flags.DEFINE_integer("frame_gap", 1, "Pair frame i with frame i + frame_gap.")
flags.DEFINE_float("min_baseline", None, "Metres; pairs by baseline range instead.")
flags.DEFINE_float("max_baseline", None, "Metres; pairs by baseline range instead.")
flags.DEFINE_integer("max_frame_gap", 30, "Farthest partner searched by baseline.")
flags.DEFINE_float("test_fraction", 0.0, "Last share of frames written as the test split.")
flags.DEFINE_enum("split", "train", ("train", "test"), "Split when test_fraction is 0.")
flags.DEFINE_string("recording", None, "Name suffix: custom_<split>_<recording>.h5.")
flags.DEFINE_integer("webp_quality", 101, "WebP quality; > 100 is lossless.")
flags.DEFINE_float(
    "max_time_difference", 0.02, "Seconds from an image's time stamp to the one matched to it."
)
flags.DEFINE_enum(
    "match_frames",
    "auto",
    recordings.MATCH_FRAMES,
    "How poses, depth images and range readings find their image: auto (same name, else "
    "time stamp when both have one, else order), time (nearest time stamp) or order (the "
    "i-th for the i-th image).",
)
flags.DEFINE_bool("overwrite", False, "Replace output files that exist already.")


def main(argv: Sequence[str]) -> None:
    del argv
    values = flags.FLAGS
    try:
        result = _write(values)
    except (ValueError, FileNotFoundError, FileExistsError) as error:
        # The recording given cannot be converted as asked (the message names the file,
        # its line or the flag); nothing was written.
        raise ArgumentError(str(error)) from error
    for split_name, path in result["files"].items():
        print(f"{path}: {result['pairs'][split_name]} pairs ({split_name})")
    for reason, count in result["dropped"].items():
        print(f"pairs left out, {reason}: {count}")
    for path in result["removed"]:
        print(f"{path}: removed (the same recording's earlier split, whose pairs would overlap)")


def _write(values: flags.FlagValues) -> dict:
    return writer.write_recording(
        values.images,
        values.poses,
        values.intrinsics,
        values.output_dir,
        depth=values.depth,
        pose_format=values.pose_format,
        pose_direction=values.pose_direction,
        depth_scale=values.depth_scale,
        depth_metric=values.depth_metric,
        frame_gap=values.frame_gap,
        min_baseline=values.min_baseline,
        max_baseline=values.max_baseline,
        max_frame_gap=values.max_frame_gap,
        test_fraction=values.test_fraction,
        split=values.split,
        recording=values.recording,
        webp_quality=values.webp_quality,
        max_time_difference=values.max_time_difference,
        match_frames=values.match_frames,
        overwrite=values.overwrite,
    )


if __name__ == "__main__":
    command_line.run(main)
