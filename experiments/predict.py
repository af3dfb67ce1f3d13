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
`--range_metric=ray_length` the distance along the pixel's ray): each pair is scaled by
its first frame's readings (the median ratio of reading to predicted depth). `--poses`, a
TUM trajectory (`timestamp tx ty tz qx qy qz qw`; images named by time stamp are
matched by time, otherwise the i-th pose is the i-th frame): each pair is scaled by the
distance between its frames' positions, and a model trained given the relative pose
(`--global_source=pose`) is given the pair's relative pose from the trajectory (it
needs `--poses`); a model trained on the pose from its flow (`--global_source=flow_pose`)
needs `--intrinsics`, as does one that refines its encoder's pose on the flow
(`--pose_refinement_steps`). Pairs without a reading on the first frame, or
with a baseline not above `--min_baseline`, are skipped and counted. With neither,
depth is in units of the (unknown) baseline and written as .npy.

Writes to `--output_dir` (see `gld.inference.predict`): depth/<frame1>__<frame2>.png (16-bit,
millimetres; `--format=png`, the default for metric depth) or .npy (float32, the
default without a scale), preview/ (`--previews`), ply/ (`--ply`, needs
`--intrinsics`: fx,fy,cx,cy in pixels or a file with 4 numbers or a 3x3 K), pairs.csv
and summary.json. Every flag is checked before the model is loaded or a file is written.

`--measure_scale` instead measures how well metric depth is recovered on the test pairs
of `--dataset` (default: the workdir's), whose records hold true depth and pose: the
metric Abs-Rel with the true baseline, with one range reading at a random valid pixel,
with the training set's mean baseline, and with each pair's best scale (a reference that
sees the truth); printed and, with `--output_dir`, written to scale_recovery.json/.md.
"""

from __future__ import annotations

import json
from pathlib import Path

from absl import app, flags

from experiments import common
from gld.inference import inputs
from gld.inference import recordings as recording_lib

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
flags.DEFINE_bool("ply", False, "Also write a PLY point cloud per pair (needs --intrinsics).")
flags.DEFINE_string("intrinsics", None, "fx,fy,cx,cy in pixels of the frames, or a file.")
flags.DEFINE_string("ranges", None, "Range readings CSV frame,u,v,depth (metric scale).")
flags.DEFINE_float("range_scale", 1.0, "Metres per unit of the CSV's depth column.")
flags.DEFINE_enum(
    "range_metric",
    "camera_z",
    ["camera_z", "ray_length"],
    "What the CSV's depth is: camera-z depth, or the distance along the pixel's ray (a "
    "range sensor's beam; needs --intrinsics).",
)
flags.DEFINE_string("poses", None, "TUM trajectory: baseline = distance between frames.")
flags.DEFINE_float("max_time_difference", 0.02, "Seconds between image and pose stamps.")
flags.DEFINE_float("min_baseline", 0.0, "Metres; pairs whose baseline is not above are skipped.")
flags.DEFINE_integer("batch_size", 8, "Pairs per jit-compiled model call.")
flags.DEFINE_enum(
    "aspect",
    "resize",
    ["resize", "crop"],
    "Frames of another aspect ratio than the model's: stretch them (a warning says by how "
    "much) or use their centred crop (no depth outside it).",
)
flags.DEFINE_bool("measure_scale", False, "Measure metric scale recovery on a dataset instead.")
flags.DEFINE_integer("max_examples", 0, "--measure_scale: the first N test pairs (0 = all).")
flags.DEFINE_integer("seed", 0, "--measure_scale: seeds the range reading's pixel.")
common.define_data_flags(default_dataset=None)


def _usage(flag: str, error: Exception) -> app.UsageError:
    return app.UsageError(f"--{flag}: {error}")


def _frames():
    """The frame source and the image paths (None for a video), checked."""
    from data.demon import recordings

    if bool(FLAGS.images) == bool(FLAGS.video):
        raise app.UsageError("give exactly one of --images (a folder) or --video (a file)")
    cache_size = FLAGS.batch_size + FLAGS.frame_gap + 2
    if FLAGS.images:
        try:
            paths = recordings.list_images(Path(FLAGS.images).expanduser())
        except FileNotFoundError as error:
            raise _usage("images", error) from None
        return recording_lib.ImageFolderFrames(paths, cache_size=cache_size), paths
    try:
        return recording_lib.VideoFrames(
            Path(FLAGS.video).expanduser(), cache_size=cache_size
        ), None
    except (FileNotFoundError, ValueError) as error:
        raise _usage("video", error) from None


def _camera_poses(image_paths, names) -> object:
    """[F, 4, 4] camera-to-world poses of the frames from the --poses trajectory."""
    from data.demon import recordings

    try:
        timestamps, camera_to_world = recordings.read_tum_trajectory(Path(FLAGS.poses).expanduser())
        indices = recordings.associate_poses(
            image_paths or [Path(name) for name in names],
            timestamps if image_paths else None,
            len(camera_to_world),
            FLAGS.max_time_difference,
        )
    except (FileNotFoundError, ValueError) as error:
        raise _usage("poses", error) from None
    return camera_to_world[indices]


def _model_inputs() -> tuple[str, ...]:
    """The inputs the workdir's model reads besides the images and flow (its
    `extra_inputs`: a given pose, or the cameras), from its stored config."""
    from gld.models import registry
    from gld.runs import workdir as workdir_lib

    try:
        config = workdir_lib.load_run_config(FLAGS.workdir)
    except (FileNotFoundError, ValueError) as error:
        raise _usage("workdir", error) from None
    return tuple(
        getattr(registry.make_model(config.model, **config.model_config), "extra_inputs", ())
    )


def _measure_scale() -> None:
    from gld import input_pipeline
    from gld.inference import scale
    from gld.inference.predict import DepthPredictor
    from gld.runs import workdir as workdir_lib

    try:
        config = workdir_lib.load_run_config(FLAGS.workdir)
    except FileNotFoundError as error:
        raise _usage("workdir", error) from None
    builder = common.prepare_dataset(FLAGS.dataset or config.dataset)
    if "train" not in builder.info.splits or "test" not in builder.info.splits:
        raise _usage("dataset", ValueError(f"{builder.info.full_name} needs train and test splits"))
    decoders = input_pipeline.source_decoders()
    test_source = builder.as_data_source("test", decoders=decoders)
    train_source = builder.as_data_source("train", decoders=decoders)
    predictor = DepthPredictor.from_workdir(FLAGS.workdir, step=FLAGS.step)
    from tqdm import tqdm

    total = len(test_source) if FLAGS.max_examples <= 0 else FLAGS.max_examples
    with tqdm(total=min(total, len(test_source)), desc="scale", unit="pair") as bar:
        result = scale.measure_scale_recovery(
            lambda image1, image2, flow: predictor(image1, image2, flow),
            test_source,
            train_source,
            seed=FLAGS.seed,
            batch_size=FLAGS.batch_size,
            max_examples=FLAGS.max_examples,
            progress=lambda done: bar.update(done - bar.n),
        )
    table = scale.scale_table(result)
    print(f"{builder.info.full_name}, workdir {FLAGS.workdir}\n{table}")
    if FLAGS.output_dir:
        out_dir = Path(FLAGS.output_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        stored = {
            "dataset": builder.info.full_name,
            "workdir": str(FLAGS.workdir),
            "seed": FLAGS.seed,
            **result,
        }
        (out_dir / "scale_recovery.json").write_text(json.dumps(stored, indent=2) + "\n")
        (out_dir / "scale_recovery.md").write_text(table + "\n")


def main(argv):
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    common.initialise()
    if FLAGS.measure_scale:
        _measure_scale()
        return
    from data.demon import recordings
    from gld.inference import predict
    from gld.runs import workdir as workdir_lib

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
    metric = bool(FLAGS.ranges or FLAGS.poses)
    depth_format = FLAGS.format or ("png" if metric else "npy")
    if depth_format == "png" and not metric:
        raise app.UsageError(
            "--format=png writes millimetres and needs metric depth: give --ranges or "
            "--poses, or use --format=npy"
        )
    if FLAGS.range_metric == "ray_length" and not FLAGS.intrinsics:
        raise app.UsageError("--range_metric=ray_length needs --intrinsics")
    if FLAGS.ply and not FLAGS.intrinsics:
        raise app.UsageError("--ply needs --intrinsics (fx,fy,cx,cy in pixels, or a file)")
    camera_matrix = None
    if FLAGS.intrinsics:
        try:
            camera_matrix = recordings.read_intrinsics(FLAGS.intrinsics)
        except ValueError as error:
            raise _usage("intrinsics", error) from None
    try:
        workdir_lib.load_run_config(FLAGS.workdir)
    except FileNotFoundError as error:
        raise _usage("workdir", error) from None

    frames, image_paths = _frames()
    try:
        first_frame = frames.read(0)
        inputs.check_image(first_frame, f"frame {frames.names[0]}")
    except ValueError as error:
        raise _usage("images" if FLAGS.images else "video", error) from None
    image_size = first_frame.shape[:2]
    try:
        if FLAGS.pairs:
            pairs = recording_lib.read_pairs_file(Path(FLAGS.pairs).expanduser(), frames.names)
        else:
            pairs = recording_lib.frame_pairs(len(frames), FLAGS.frame_gap)
    except (FileNotFoundError, ValueError) as error:
        raise _usage("pairs" if FLAGS.pairs else "frame_gap", error) from None
    ranges = camera_to_world = None
    if FLAGS.ranges:
        try:
            ranges = recording_lib.read_range_readings(
                Path(FLAGS.ranges).expanduser(), frames.names, image_size, FLAGS.range_scale
            )
        except (FileNotFoundError, ValueError, OSError) as error:
            raise _usage("ranges", error) from None
        if FLAGS.range_metric == "ray_length":
            from gld.inference import scale

            for readings in ranges.values():
                readings[:, 2] = scale.ray_length_to_depth(
                    readings[:, :2], readings[:, 2], camera_matrix
                )
    if FLAGS.poses:
        camera_to_world = _camera_poses(image_paths, frames.names)
    from gld.models import global_local as model_lib

    model_inputs = _model_inputs()
    if model_inputs == model_lib.POSE_INPUTS and camera_to_world is None:
        raise _usage(
            "poses",
            ValueError(
                "the model was trained given the relative pose: give the recording's "
                "odometry as a TUM trajectory"
            ),
        )
    if set(model_inputs) - set(model_lib.POSE_INPUTS) and camera_matrix is None:
        raise _usage(
            "intrinsics",
            ValueError(
                "the model takes the camera motion from its flow's geometry, which needs the camera"
            ),
        )
    try:
        plan = recording_lib.plan_recording(
            pairs,
            ranges=ranges,
            camera_to_world=camera_to_world,
            min_baseline=FLAGS.min_baseline,
        )
    except ValueError as error:
        raise _usage("ranges" if FLAGS.ranges else "poses", error) from None

    from tqdm import tqdm

    predictor = predict.DepthPredictor.from_workdir(
        FLAGS.workdir, step=FLAGS.step, aspect=FLAGS.aspect
    )
    with tqdm(total=len(plan.pairs), desc="predict", unit="pair") as bar:
        summary = recording_lib.predict_recording(
            predictor,
            frames,
            plan,
            Path(FLAGS.output_dir).expanduser(),
            batch_size=FLAGS.batch_size,
            depth_format=depth_format,
            previews=FLAGS.previews,
            camera_matrix=camera_matrix,
            ply=FLAGS.ply,
            progress=bar.update,
        )
    frames.close()
    skipped = sum(summary["pairs_skipped"].values())
    print(
        f"{summary['pairs_written']} pair(s) written to {FLAGS.output_dir} "
        f"({summary['units']}, {depth_format}); {skipped} skipped"
        + "".join(
            f", {count} {reason}" for reason, count in summary["pairs_skipped"].items() if count
        )
    )


if __name__ == "__main__":
    app.run(main)
