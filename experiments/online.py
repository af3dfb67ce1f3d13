r"""Learns depth online, on a robot's stream of frames, odometry and range readings.

    python -m experiments.online --workdir=runs/online --frames=5000
    python -m experiments.online --workdir=runs/shifted --world=shifted \
        --pretrained=runs/demo --frames=1000               # adapt a trained model
    python -m experiments.online --workdir=runs/frozen --pretrained=runs/demo --nolearn
    python -m experiments.online --workdir=runs/photometric --model=struct2depth_flow
    python -m experiments.online --workdir=runs/rec --images=rec/rgb --poses=rec/poses.txt \
        --ranges=rec/range.csv --intrinsics=517.3,516.5,318.6,255.3 --size=96x128

The stream: a simulated robot in a `gld_scenes` world (`data.gld_scenes.robot_stream`:
`--world=training` like the training worlds, or `shifted`; `--seed`), or a recording in
the formats of `experiments.predict` (`--images` or `--video`, `--poses` as a TUM
trajectory, `--ranges` as `frame,u,v,depth`, `--intrinsics`), its frames resized to
`--size`. The learner (`gld.online.learner`): each frame's depth is predicted with the
model as it is and scored against the truth where there is one (prequential: before the
learner trains on the frame), then the pair with its range reading joins a bounded
replay buffer and `--updates_per_frame` Adam steps run on batches of the newest and
replayed pairs, beside the next frames' predictions. The model: `--pretrained` (a
training workdir: its model and weights), or a new one (`--model`: the main job's
global-local model and loss, or `struct2depth[_flow]`, the self-supervised baseline's
photometric route, which reads no range). `--nolearn` keeps it frozen. On the CPU the
updates run data-parallel over `--cpu_devices` devices and the predictions on one more.
`--references` also scores, on each of the learner's pairs, the classical pipeline on
its flow (`sfm_flow`) and the flow triangulated under the true pose (simulation only).

Writes to `--workdir` (`gld.online.run`): prequential.jsonl, checkpoints/, summary.json
(speed and the curve), curve.png and, with `--view_every=N`, view/ (the frame, the
prediction, its error, the labelled pixel). A run launched again on its workdir resumes
from its newest checkpoint with the same result as an uninterrupted one; one with more
`--frames` continues.
"""

from __future__ import annotations

import json
from pathlib import Path

from absl import app, flags

from data import command_line

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", None, "Where the run is written (and resumed from).")
flags.DEFINE_integer("frames", 5000, "Frames of the stream to learn from.", lower_bound=1)
flags.DEFINE_enum("world", "training", ["training", "shifted"], "The simulated robot's world.")
flags.DEFINE_integer("seed", 0, "The simulated world and trajectory, and the learner's sampling.")
flags.DEFINE_float(
    "camera_yaw",
    0.0,
    "The simulated camera's heading from the direction of travel, degrees (90: sideways).",
)
flags.DEFINE_list(
    "reading_pixel",
    None,
    "u,v: the simulated range sensor's pixel (default: the image centre, where a forward-"
    "looking robot's flow has its expansion's centre).",
)
flags.DEFINE_string("size", "96x128", "HEIGHTxWIDTH of the frames (a new model's resolution).")
flags.DEFINE_string("pretrained", None, "A training workdir to start from (its model).")
flags.DEFINE_enum(
    "model",
    "global_local",
    ["global_local", "struct2depth", "struct2depth_flow"],
    "A new model: the main job's global-local model and loss, or the self-supervised "
    "baseline (photometric loss, no range reading), without or with the flow.",
)
flags.DEFINE_enum(
    "global_source",
    "encoder",
    ["encoder", "pose", "flow_pose"],
    "A new global-local model's g: its encoder (the main job's: a teacher and refinement on "
    "the flow), the robot's odometry (pose), or the flow's essential matrix (flow_pose).",
)
flags.DEFINE_bool("learn", True, "Learn online (--nolearn: the frozen reference).")
flags.DEFINE_bool(
    "references",
    False,
    "Also score the classical references on each pair (simulation only): the essential "
    "matrix's pipeline on the pair's flow (sfm_flow) and the flow triangulated under the "
    "true pose; their columns and curve in the run's summary.",
)
flags.DEFINE_integer("updates_per_frame", 1, "Adam steps after each frame.", lower_bound=0)
flags.DEFINE_integer("batch_size", 4, "Pairs per update.", lower_bound=1)
flags.DEFINE_integer("capacity", 256, "Pairs the replay buffer holds.", lower_bound=1)
flags.DEFINE_float(
    "zoom", 0.5, "Replayed pairs are random crops of at least this much of each side (1: none)."
)
flags.DEFINE_float(
    "learning_rate", 5e-4, "Adam's learning rate, constant after --warmup.", lower_bound=0
)
flags.DEFINE_integer(
    "warmup", 0, "Updates over which the rate rises linearly from 0 (0: none).", lower_bound=0
)
flags.DEFINE_float(
    "anchor",
    0.0,
    "Each update also takes this fraction of every parameter's distance from its starting "
    "(pretrained) value back (L2-SP); 0: none.",
    lower_bound=0,
)
flags.DEFINE_integer(
    "reading_memory",
    0,
    "Earlier frames whose range readings, carried by the odometry, also label each frame.",
    lower_bound=0,
)
flags.DEFINE_integer(
    "teacher_labels",
    0,
    "Labels a pair also gets from the classical pipeline on its own flow (the essential "
    "matrix's pose, triangulated where the parallax is large); 0: none.",
    lower_bound=0,
)
flags.DEFINE_float(
    "teacher_parallax", 1.0, "Pixels of parallax a teacher's label needs.", lower_bound=0.0
)
flags.DEFINE_float("min_baseline", 0.05, "Metres of odometry between a frame and its partner.")
flags.DEFINE_integer("max_partner_gap", 20, "Frames back a partner may be.", lower_bound=1)
flags.DEFINE_float(
    "max_rotation",
    0.0,
    "Degrees the odometry may turn between a frame and its partner (a nearer partner in a "
    "sharp turn; 0 = any).",
    lower_bound=0.0,
)
flags.DEFINE_bool("asynchronous", True, "Updates in a worker thread beside prediction.")
flags.DEFINE_integer(
    "cpu_devices",
    2,
    "On the CPU, JAX devices the updates are split over (data parallelism over the cores; "
    "lowered to the largest count that divides --batch_size); predictions run on one more "
    "device of their own, so that an update never holds them up.",
    lower_bound=1,
)
flags.DEFINE_integer("checkpoint_every", 250, "Frames between checkpoints.", lower_bound=1)
flags.DEFINE_integer("window", 250, "Frames per point of the curve.", lower_bound=1)
flags.DEFINE_integer(
    "view_every", 0, "Write the view of every N-th frame (0: none).", lower_bound=0
)
flags.DEFINE_bool("progress", True, "Show a progress bar.")
flags.DEFINE_string(
    "offline_reference_of",
    None,
    "Instead of learning online: the offline reference of this online run's workdir (its "
    "frames and gradient steps, shuffled; both final models scored on the frames), written "
    "to --workdir/offline_reference.json. Give the run's stream and learner flags.",
)
# A recording instead of the simulated robot.
flags.DEFINE_string("images", None, "A recording's frames: a folder of images.")
flags.DEFINE_string("video", None, "A recording's frames: a video file.")
flags.DEFINE_string("poses", None, "The recording's TUM trajectory (its odometry).")
flags.DEFINE_string("ranges", None, "The recording's range CSV (frame,u,v,depth).")
flags.DEFINE_float("range_scale", 1.0, "Range CSV depth x this = metres.")
flags.DEFINE_string("intrinsics", None, "fx,fy,cx,cy of the recording's frames (pixels).")
flags.DEFINE_float("frame_rate", 10.0, "The recording's frames per second.", lower_bound=0)
flags.DEFINE_enum(
    "match_frames",
    "auto",
    ["auto", "time", "order"],
    "How poses and readings find their frame, as experiments.predict's --match_frames.",
)
flags.mark_flag_as_required("workdir")


def _size() -> tuple[int, int]:
    height, _, width = FLAGS.size.partition("x")
    if not (height.isdigit() and width.isdigit() and int(height) >= 8 and int(width) >= 8):
        raise app.UsageError(
            f"--size: {FLAGS.size!r} is not HEIGHTxWIDTH of 8 or more, e.g. 96x128"
        )
    return int(height), int(width)


# The flags of the simulated robot alone.
# The flags that only the simulated robot reads, and why a recording refuses each.
_SETS_THE_ROBOT = "sets the simulated robot; a recording has its own camera and readings"
SIMULATOR_FLAGS = {
    "world": _SETS_THE_ROBOT,
    "camera_yaw": _SETS_THE_ROBOT,
    "reading_pixel": _SETS_THE_ROBOT,
    "references": "scores against the simulator's truth; a recording has none",
}


def _stream(height: int, width: int):
    """The simulated robot, or the recording the flags name."""
    if FLAGS.images or FLAGS.video:
        simulated = [name for name in SIMULATOR_FLAGS if FLAGS[name].present]
        if simulated:
            raise app.UsageError(f"--{simulated[0]} {SIMULATOR_FLAGS[simulated[0]]}")
        from data.demon import recordings as recording_files
        from gld.online import recording_stream

        return recording_stream.open_recording(
            recording_files,
            images=FLAGS.images,
            video=FLAGS.video,
            poses=FLAGS.poses,
            ranges=FLAGS.ranges,
            range_scale=FLAGS.range_scale,
            intrinsics=FLAGS.intrinsics,
            frame_rate=FLAGS.frame_rate,
            height=height,
            width=width,
            match_frames=FLAGS.match_frames,
        )
    from data.gld_scenes import robot_stream

    try:
        settings = robot_stream.RobotSettings(
            height=height,
            width=width,
            world=FLAGS.world,
            camera_yaw_degrees=FLAGS.camera_yaw,
            reading_pixel=_reading_pixel(),
        )
    except ValueError as error:
        raise app.UsageError(str(error)) from None
    return robot_stream.SimulatedRobot(FLAGS.seed, settings)


def _reading_pixel() -> tuple[int, int] | None:
    if FLAGS.reading_pixel is None:
        return None
    try:
        u, v = (int(value) for value in FLAGS.reading_pixel)
    except ValueError:
        raise app.UsageError(
            f"--reading_pixel must be two integers u,v, got {','.join(FLAGS.reading_pixel)}"
        ) from None
    return u, v


def _model(height: int, width: int):
    """(model, variables, loss weights, what it is) of --pretrained or a new model."""
    from gld.losses.supervised import LossWeights
    from gld.models import registry
    from gld.runs import recipe, state
    from gld.runs import workdir as workdir_lib

    if FLAGS.global_source != "encoder" and (FLAGS.pretrained or FLAGS.model != "global_local"):
        raise app.UsageError(
            f"--global_source={FLAGS.global_source} makes a new global-local model: it does not "
            "go with --pretrained or another --model"
        )
    if FLAGS.pretrained:
        model, variables, config = workdir_lib.load_trained(FLAGS.pretrained)
        if (config.height, config.width) != (height, width):
            raise app.UsageError(
                f"--pretrained={FLAGS.pretrained} runs at {config.height}x{config.width}, the "
                f"stream is {height}x{width}: give --size={config.height}x{config.width}"
            )
        return model, variables, config.loss_weights(), f"{config.model} from {FLAGS.pretrained}"
    architecture: dict[str, object] = {}
    if FLAGS.model != "global_local":
        from gld.losses.photometric import SelfSupervisedWeights

        model = registry.make_model(FLAGS.model)
        weights = SelfSupervisedWeights()
    elif FLAGS.global_source != "encoder":
        # A given pose: no encoder to teach, nothing to refine; read against the flow as
        # the encoder's would be.
        architecture = {**recipe.ARCHITECTURE_GIVEN_POSE, "global_source": FLAGS.global_source}
        model = registry.make_model("global_local", **architecture)
        weights = LossWeights(epipolar=0.0, pose_teacher=0.0)
    else:
        architecture = recipe.ARCHITECTURE
        model = registry.make_model("global_local", **architecture)
        weights = LossWeights(
            epipolar=recipe.MOTION_WEIGHTS["epipolar_weight"],
            pose_teacher=recipe.MOTION_WEIGHTS["pose_teacher_weight"],
        )
    variables = state.init_variables(model, height, width, FLAGS.seed)
    source = "" if FLAGS.global_source == "encoder" else f", g from {FLAGS.global_source}"
    # The architecture is part of the description, which a resumed run must share: a run
    # begun under another recipe is refused, not continued with other options.
    options = ", ".join(f"{name}={value}" for name, value in sorted(architecture.items()))
    return (
        model,
        variables,
        weights,
        f"{FLAGS.model} from scratch{source}" + (f" ({options})" if options else ""),
    )


def _offline_reference(stream, model, variables, settings, size, weights, learner) -> None:
    """The offline reference of --offline_reference_of's run (`gld.online.offline`)."""
    import dataclasses

    from gld.online import checkpoint, offline, run

    online = Path(FLAGS.offline_reference_of)
    summary_path = online / run.SUMMARY_FILE
    if not summary_path.is_file():
        raise app.UsageError(f"--offline_reference_of: {summary_path} not found (a finished run?)")
    summary = json.loads(summary_path.read_text())
    checkpoints = checkpoint.manager(online)
    try:
        if checkpoint.restore(checkpoints, learner) is None:
            raise app.UsageError(f"--offline_reference_of: {online} holds no checkpoint")
    finally:
        checkpoints.close()

    def make_learner(**changes):
        start = changes.pop("variables", variables)
        changed = dataclasses.replace(settings, **changes)
        return learner_lib.OnlineLearner(model, start, changed, *size, weights)

    from gld.online import learner as learner_lib

    result = offline.offline_reference(
        stream,
        make_learner,
        frames=summary["frames"],
        updates=summary["updates"],
        online_variables=learner.published,
    )
    output = Path(FLAGS.workdir) / "offline_reference.json"
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps({"online_run": str(online), **result}, indent=1) + "\n")
    print(json.dumps(result))
    print(f"wrote {output}")


def main(argv: list[str]) -> None:
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    if FLAGS.images and FLAGS.video:
        raise app.UsageError("give --images or --video, not both")
    height, width = _size()
    from absl import logging

    from gld import sharding

    if not FLAGS["verbosity"].present:
        logging.set_verbosity(logging.WARNING)  # orbax's progress lines
    sharding.split_cpu_devices(1 + sharding.devices_for_batch(FLAGS.batch_size, FLAGS.cpu_devices))
    from gld.online import learner as learner_lib
    from gld.online import references, run

    try:
        settings = learner_lib.OnlineSettings(
            min_baseline=FLAGS.min_baseline,
            max_partner_gap=FLAGS.max_partner_gap,
            max_rotation=FLAGS.max_rotation,
            batch_size=FLAGS.batch_size,
            updates_per_frame=FLAGS.updates_per_frame,
            capacity=FLAGS.capacity,
            zoom=FLAGS.zoom,
            learning_rate=FLAGS.learning_rate,
            warmup=FLAGS.warmup,
            anchor=FLAGS.anchor,
            reading_memory=FLAGS.reading_memory,
            teacher_labels=FLAGS.teacher_labels,
            teacher_parallax=FLAGS.teacher_parallax,
            learn=FLAGS.learn,
            references=FLAGS.references,
            asynchronous=FLAGS.asynchronous,
            seed=FLAGS.seed,
        )
    except ValueError as error:
        raise app.UsageError(str(error)) from None
    stream = _stream(height, width)
    model, variables, weights, described = _model(height, width)
    learner = learner_lib.OnlineLearner(model, variables, settings, height, width, weights)
    if FLAGS.offline_reference_of:
        _offline_reference(stream, model, variables, settings, (height, width), weights, learner)
        return
    meta = {
        "name": Path(FLAGS.workdir).name,
        "model": described,
        "learn": FLAGS.learn,
        "devices": learner.devices,
        "stream": stream.describe(),
        "settings": {key: getattr(settings, key) for key in settings.__dataclass_fields__},
    }
    summary = run.run_online(
        stream,
        learner,
        FLAGS.workdir,
        frames=FLAGS.frames,
        meta=meta,
        checkpoint_every=FLAGS.checkpoint_every,
        window=FLAGS.window,
        view_every=FLAGS.view_every,
        progress=FLAGS.progress,
    )
    speed = {
        key: summary[key]
        for key in (
            "frames_per_second",
            "sustained_frames_per_second",
            "frame_ms",
            "latency_ms",
            "update_wait_ms",
        )
    }
    print(json.dumps(speed))
    for point in summary["curve"]:
        print(
            f"frames {point['frames']:6d}: Abs-Inv {point['abs_inv']:.4f} "
            f"(running mean {point['abs_inv_mean']:.4f}, {point['x_mean']:.2f}x mean; "
            f"median frame {point['median_x_mean']:.2f}x)"
            + "".join(
                f"; {name} {point[f'{name}_x_mean']:.2f}x, median frame "
                f"{point[f'{name}_median_x_mean']:.2f}x"
                for name in references.NAMES
                if f"{name}_x_mean" in point
            )
        )
    print(f"wrote {Path(FLAGS.workdir) / run.SUMMARY_FILE}")


if __name__ == "__main__":
    command_line.run(main)
