r"""Trains a depth model and evaluates it: `python -m experiments.train [--flagfile=...]`.

With no flags this is the demo: it builds the embedded benchmark `gld_scenes/small` on
first use, trains the global-local model with ONE supervised pixel per image, evaluates
it and the dataset-mean baseline on the test split and leaves everything in runs/demo.
Re-running the same command resumes from the last checkpoint.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "Run directory (checkpoints, logs, eval).")
flags.DEFINE_string("model", "global_local", "Model name (gld.model.MODELS).")
flags.DEFINE_bool("final_eval", True, "Evaluate the final model on the whole test split.")
flags.DEFINE_integer("num_figures", 8, "Example figures written by the final evaluation.")
# Architecture of the global-local model (the paper's numbers are the defaults).
flags.DEFINE_list("encoder_channels", ["16", "32", "64", "128", "256"], "Global encoder channels.")
flags.DEFINE_list("encoder_strides", ["2", "2", "2", "2", "1"], "Global encoder strides.")
flags.DEFINE_integer("global_dim", 6, "Size of the global parameter vector.")
flags.DEFINE_list("bank_channels", ["20", "10", "20"], "Output channels of the generated banks.")
flags.DEFINE_integer("kernel_size", 3, "Kernel size of generated filters and the final conv.")
flags.DEFINE_bool("use_image_pair", True, "Ablation switch: image pair into the global module.")
flags.DEFINE_bool("use_coordinates", True, "Ablation switch: CoordConv channels.")
flags.DEFINE_bool("use_global_module", True, "Ablation switch: filters generated from g.")
flags.DEFINE_bool("use_flow", True, "Ablation switch: optical flow as the local input.")
flags.DEFINE_enum(
    "local_flow_units", "normalised", ["normalised", "pixels"], "Units of the local network flow."
)
flags.DEFINE_float("flow_scale", 10.0, "Factor on the normalised flow fed to both modules.")
flags.DEFINE_enum("global_norm", "none", ["none", "batch"], "Normalisation of g.")
flags.DEFINE_float("modulation_scale", 0.2, "Initial modulation of the filters by g.")
flags.DEFINE_string(
    "filter_formulation", None, "apply_filter_banks formulation (default: fastest here)."
)
# The main job's recipe: the best measured within its 15-minute CPU budget (Adam 1e-3,
# warm-up and cosine decay; WORKSPACE.md). Paper flagfiles set Adam 1e-4, constant.
common.define_training_flags(
    steps=2000, eval_every=1000, learning_rate=1e-3, lr_schedule="cosine", warmup_steps=100
)
common.define_data_flags()
common.define_distributed_flags()


def model_config_from_flags() -> dict:
    """Constructor arguments of the selected model from the architecture flags."""
    if FLAGS.model != "global_local":
        return {}
    config = {
        "encoder_channels": [int(c) for c in FLAGS.encoder_channels],
        "encoder_strides": [int(s) for s in FLAGS.encoder_strides],
        "global_dim": FLAGS.global_dim,
        "bank_channels": [int(c) for c in FLAGS.bank_channels],
        "kernel_size": FLAGS.kernel_size,
        "use_image_pair": FLAGS.use_image_pair,
        "use_coordinates": FLAGS.use_coordinates,
        "use_global_module": FLAGS.use_global_module,
        "use_flow": FLAGS.use_flow,
        "local_flow_units": FLAGS.local_flow_units,
        "flow_scale": FLAGS.flow_scale,
        "global_norm": FLAGS.global_norm,
        "modulation_scale": FLAGS.modulation_scale,
    }
    if FLAGS.filter_formulation:
        config["filter_formulation"] = FLAGS.filter_formulation
    return config


def main(argv):
    del argv
    common.initialise()
    from gld import train

    builder = common.prepare_dataset()
    height, width = common.dataset_resolution(builder)
    config = train.TrainConfig(
        model=FLAGS.model,
        model_config=model_config_from_flags(),
        dataset=FLAGS.dataset,
        height=height,
        width=width,
        **common.training_options(),
    )
    common.write_flags(FLAGS.workdir)
    print(
        f"dataset {FLAGS.dataset}: {builder.info.splits['train'].num_examples} train / "
        f"{builder.info.splits['test'].num_examples} test pairs at {width}x{height}"
    )
    train.train_and_evaluate(
        config,
        FLAGS.workdir,
        common.data_source(builder, "train"),
        common.data_source(builder, "test"),
    )
    if FLAGS.final_eval:
        from gld import evaluation

        evaluation.evaluate_workdir(
            FLAGS.workdir,
            common.data_source(builder, "test"),
            train_source=common.data_source(builder, "train"),
            dataset=builder.info.full_name,
            height=height,
            width=width,
            num_figures=FLAGS.num_figures,
        )


if __name__ == "__main__":
    app.run(main)
