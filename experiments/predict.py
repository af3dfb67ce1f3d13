r"""Predicts depth for every frame pair of a recording with a trained workdir.

    python -m experiments.predict --workdir=runs/robot --images=rec/rgb \
        --ranges=rec/range.csv --intrinsics=517.3,516.5,318.6,255.3 --output_dir=out \
        [--frame_gap=N | --pairs=pairs.txt] [--format=png|npy] [--previews] [--ply]
    python -m experiments.predict --workdir=runs/robot --video=rec.mp4 --poses=rec/poses.txt \
        --output_dir=out
    python -m experiments.predict --workdir=runs/demo --measure_scale [--output_dir=out]

Frames: `--images` (a folder, name order = time order; frames named by file stem) or
`--video` (read with OpenCV; frames named 000000, 000001, ...). Pairs: frame i with
frame i + `--frame_gap` (default consecutive), or the `--pairs` file (one
`frame1 frame2` per line, by name or index). Frames are streamed: a long recording is
never held in memory.

Scale: `--ranges`, the range CSV of `data.demon.convert` (`frame,u,v,depth`, depth x
`--range_scale` = metres, pixels of the frame; camera-z depth, or with
`--range_metric=ray_length` the distance along the pixel's ray): a pair (i, j) is frame
i's depth and is scaled by frame i's readings (the median ratio of reading to predicted
depth). That is the converter's rule: its records supervise frame i's depth with frame
i's readings. Frame j's readings are not used here; the converter needs one on frame j
too only because the dataset's reader refuses a view without depth. `--poses`, a TUM
trajectory (`timestamp tx ty tz qx qy qz qw`): each pair is scaled by the distance
between its frames' positions, and a model trained given the relative pose
(`--global_source=pose`) is given the pair's relative pose from the trajectory (it
needs `--poses`); a model trained on the pose from its flow (`--global_source=flow_pose`)
needs `--intrinsics`, as does one that refines its encoder's pose on the flow
(`--pose_refinement_steps`), derotates the flow or triangulates it under a pose (its
encoder's or a given one: a model given the relative pose that does needs both).
Pairs without a reading on the first frame, or with a baseline not above
`--min_baseline`, are skipped and counted. With neither,
depth is in units of the (unknown) baseline and written as .npy.

Matching frames, `--match_frames` (as in `data.demon.convert`): `auto` (default) takes
a reading's frame by name or index, and a pose by time stamp when the images are named
by one (a plain decimal number, TUM's `1305031102.175304.png`), else by order; `time`
matches poses and readings by time stamp (within `--max_time_difference` seconds),
refused when a name is not one; `order` gives the i-th frame the i-th pose and the i-th
frame of the readings (in the order the CSV first names them), refused when the counts
differ: for images numbered by frame (`000000.png`) beside a timestamped trajectory.
A video's frames have no time stamps (`time` is refused).

Writes to `--output_dir` (see `gld.inference.predict`): depth/<frame1>__<frame2>.png (16-bit,
millimetres; `--format=png`, the default for metric depth) or .npy (float32, the
default without a scale), preview/ (`--previews`), ply/ (`--ply`, needs
`--intrinsics`: fx,fy,cx,cy in pixels or a file with 4 numbers or a 3x3 K), pairs.csv
and summary.json. Every flag is checked before the model is loaded or a file is written,
and an error is one line naming what is wrong (`common.run`).

A folder holds one run (`gld.inference.prediction_folder`): the run is written whole or
not at all (a frame that fails part way leaves the folder as it was), and a folder that
holds an earlier run is refused unless `--overwrite`, which removes that run's files (and
only those: other files stay) once the new run is complete.

`--measure_scale` instead measures how well metric depth is recovered on the test pairs
of `--dataset` (default: the workdir's), whose records hold true depth and pose: the
metric Abs-Rel with the true baseline, with one range reading at a random valid pixel,
with the training set's mean baseline, and with each pair's best scale (a reference that
sees the truth); printed and, with `--output_dir`, written to scale_recovery.json/.md.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", None, "Trained workdir (config.json, checkpoints/).", required=True)
flags.DEFINE_integer("step", None, "Checkpoint step (default: latest).")
flags.DEFINE_string("images", None, "Folder of frames, in name order.")
flags.DEFINE_string("video", None, "Video file of frames (OpenCV).")
flags.DEFINE_integer("frame_gap", 1, "Pair frame i with frame i + frame_gap.")
flags.DEFINE_string("pairs", None, "File of 'frame1 frame2' lines instead of --frame_gap.")
flags.DEFINE_string("output_dir", None, "Where depth/, preview/, ply/ and the summary go.")
flags.DEFINE_enum(
    "format",
    None,
    ["png", "npy"],
    "Depth files: 16-bit PNG millimetres (needs --ranges or --poses) or float32 .npy "
    "(default: png when metric, npy otherwise).",
)
flags.DEFINE_bool("previews", False, "Also write image 1 beside its colourised inverse depth.")
flags.DEFINE_enum(
    "preview_scale",
    "pair",
    ("pair", "recording"),
    "The previews' colour scale: each pair's own, or one for the recording (the median of "
    "the pairs' own), so that colours compare across frames.",
)
flags.DEFINE_bool("ply", False, "Also write a PLY point cloud per pair (needs --intrinsics).")
flags.DEFINE_string("intrinsics", None, "fx,fy,cx,cy in pixels of the frames, or a file.")
flags.DEFINE_string(
    "ranges",
    None,
    "Range readings CSV frame,u,v,depth (metric scale): a pair is scaled by its first "
    "frame's readings; pairs without are skipped.",
)
flags.DEFINE_float("range_scale", 1.0, "Metres per unit of the CSV's depth column.")
flags.DEFINE_enum(
    "range_metric",
    "camera_z",
    ["camera_z", "ray_length"],
    "What the CSV's depth is: camera-z depth, or the distance along the pixel's ray (a "
    "range sensor's beam; needs --intrinsics).",
)
flags.DEFINE_string("poses", None, "TUM trajectory: baseline = distance between frames.")
flags.DEFINE_float(
    "max_time_difference", 0.02, "Seconds from a frame's time stamp to the one matched to it."
)
flags.DEFINE_enum(
    "match_frames",
    "auto",
    ["auto", "time", "order"],  # data.demon.recordings.MATCH_FRAMES, imported late
    "How poses and range readings find their frame: auto (readings by name or index; "
    "poses by time stamp when the images have one, else by order), time (nearest time "
    "stamp) or order (the i-th for the i-th frame).",
)
flags.DEFINE_float("min_baseline", 0.0, "Metres; pairs whose baseline is not above are skipped.")
flags.DEFINE_integer("batch_size", 8, "Pairs per jit-compiled model call.")
flags.DEFINE_enum(
    "aspect",
    "resize",
    ["resize", "crop"],
    "Frames of another aspect ratio than the model's: stretch them (a warning says by how "
    "much) or use their centred crop (no depth outside it).",
)
flags.DEFINE_bool(
    "overwrite",
    False,
    "Replace the earlier run in --output_dir (its files only); without, such a folder is refused.",
)
flags.DEFINE_bool("measure_scale", False, "Measure metric scale recovery on a dataset instead.")
flags.DEFINE_integer("max_examples", 0, "--measure_scale: the first N test pairs (0 = all).")
flags.DEFINE_integer("seed", 0, "--measure_scale: seeds the range reading's pixel.")
common.define_data_flags(default_dataset=None)


def _usage(flag: str, error: Exception) -> app.UsageError:
    return app.UsageError(f"--{flag}: {error}")


def _check_flags() -> None:
    """The flags on their own; what they name is checked by the library."""
    if not FLAGS.output_dir:
        raise app.UsageError("--output_dir is needed: where the depth files go")
    if FLAGS.batch_size < 1:
        raise _usage("batch_size", ValueError(f"must be >= 1, got {FLAGS.batch_size}"))
    if FLAGS.frame_gap < 1:
        raise _usage("frame_gap", ValueError(f"must be >= 1, got {FLAGS.frame_gap}"))
    if FLAGS.pairs and FLAGS["frame_gap"].present:
        raise app.UsageError("give --pairs or --frame_gap, not both")
    if FLAGS.ranges and FLAGS.poses:
        raise app.UsageError("give --ranges or --poses for the scale, not both")
    if not (FLAGS.range_scale > 0):
        raise _usage("range_scale", ValueError(f"must be > 0, got {FLAGS.range_scale}"))
    if _depth_format() == "png" and not (FLAGS.ranges or FLAGS.poses):
        raise app.UsageError(
            "--format=png writes millimetres and needs metric depth: give --ranges or "
            "--poses, or use --format=npy"
        )
    if FLAGS.range_metric == "ray_length" and not FLAGS.intrinsics:
        raise app.UsageError("--range_metric=ray_length needs --intrinsics")
    if FLAGS.ply and not FLAGS.intrinsics:
        raise app.UsageError("--ply needs --intrinsics (fx,fy,cx,cy in pixels, or a file)")


def _depth_format() -> str:
    return FLAGS.format or ("png" if FLAGS.ranges or FLAGS.poses else "npy")


def main(argv):
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    common.initialise()
    from data.demon import recordings
    from gld.inference import recording_run, scale_recovery

    if FLAGS.measure_scale:
        scale_recovery.measure_workdir(
            FLAGS.workdir,
            prepare_dataset=common.prepare_dataset,
            dataset=FLAGS.dataset,
            step=FLAGS.step,
            seed=FLAGS.seed,
            batch_size=FLAGS.batch_size,
            max_examples=FLAGS.max_examples,
            output_dir=FLAGS.output_dir,
        )
        return
    _check_flags()
    summary = recording_run.predict_recording_run(
        FLAGS.workdir,
        FLAGS.output_dir,
        files=recordings,
        images=FLAGS.images,
        video=FLAGS.video,
        step=FLAGS.step,
        frame_gap=FLAGS.frame_gap,
        pairs=FLAGS.pairs,
        depth_format=_depth_format(),
        previews=FLAGS.previews,
        preview_scale=FLAGS.preview_scale,
        ply=FLAGS.ply,
        intrinsics=FLAGS.intrinsics,
        ranges=FLAGS.ranges,
        range_scale=FLAGS.range_scale,
        range_metric=FLAGS.range_metric,
        poses=FLAGS.poses,
        max_time_difference=FLAGS.max_time_difference,
        match_frames=FLAGS.match_frames,
        min_baseline=FLAGS.min_baseline,
        batch_size=FLAGS.batch_size,
        aspect=FLAGS.aspect,
        overwrite=FLAGS.overwrite,
    )
    skipped = sum(summary["pairs_skipped"].values())
    print(
        f"{summary['pairs_written']} pair(s) written to {FLAGS.output_dir} "
        f"({summary['units']}, {_depth_format()}); {skipped} skipped"
        + "".join(
            f", {count} {reason}" for reason, count in summary["pairs_skipped"].items() if count
        )
    )


if __name__ == "__main__":
    common.run(main)
