r"""Trains the learned optical-flow network on the records' exact flow and compares it
with the stored DIS flow: `python -m experiments.train_flow [--flagfile=...]`.

    python -m experiments.train_flow --dataset=gld_scenes/small --workdir=runs/flow_net \
        --steps=5000

Builds the dataset on first use, trains `gld.models.flow_net.FlowNet` (PWC-Net style) against
`gt_flow`, evaluates its end-point error periodically, and finally writes
`<workdir>/eval/flow.json` and `flow_table.md`: EPE of the network and of DIS on the
test split (same pairs, same valid pixels), parameters and ms per pair. Re-running the
same command resumes from the last checkpoint.
"""

from __future__ import annotations

from absl import app, flags

from experiments import common
from gld.evaluation import flow_network

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/flow_net", "Run directory (checkpoints, logs, eval).")
flags.DEFINE_bool("final_eval", True, "Evaluate the final network on the whole test split.")
flags.DEFINE_integer(
    "latency_repeats", 30, "Timed batch-1 forward passes for the report's ms/pair.", lower_bound=1
)


def _define_flags() -> None:
    """A flag for every option of FlowTrainConfig and every FlowNet argument
    (`common.define_option_flags`), each with its one default and help."""
    from gld import options
    from gld.models.flow_net import FlowNet
    from gld.runs.flow_config import FlowTrainConfig

    common.define_option_flags(options.option_fields(FlowTrainConfig))
    common.define_option_flags(options.option_fields(FlowNet))


_define_flags()
common.define_data_flags()


def _architecture() -> dict:
    from gld import options
    from gld.models.flow_net import FlowNet

    try:
        return common.option_flag_values(options.option_fields(FlowNet))
    except ValueError as error:
        raise app.UsageError(f"--{error}") from None


def main(argv):
    if len(argv) > 1:
        raise app.UsageError(f"unexpected arguments: {argv[1:]}")
    common.initialise()
    from gld import options as options_lib
    from gld.runs import flow_config
    from gld.training import flow_trainer as flow_training

    def make_config(**values):
        options = common.option_flag_values(options_lib.option_fields(flow_config.FlowTrainConfig))
        try:
            return flow_config.FlowTrainConfig(
                **options, model_config=_architecture(), dataset=FLAGS.dataset, **values
            ).validate()
        except ValueError as error:
            raise app.UsageError(f"--{error}") from None

    # Every option is checked before the dataset is built or the workdir touched.
    make_config()
    evaluates = FLAGS.final_eval or FLAGS.eval_every > 0
    builder, height, width, train_source, test_source = common.training_data(evaluates)
    config = make_config(height=height, width=width)
    try:
        state = flow_training.train_flow(config, FLAGS.workdir, train_source, test_source)
    except ValueError as error:
        raise app.UsageError(str(error)) from None
    if not FLAGS.final_eval:
        return
    from pathlib import Path

    import jax

    table = flow_network.report_trained_flow(
        config.make_model(),
        jax.device_get(state.variables()),
        test_source,
        Path(FLAGS.workdir) / "eval",
        info={
            "dataset": builder.info.full_name,
            "split": "test",
            "step": int(jax.device_get(state.step)),
            "height": height,
            "width": width,
        },
        batch_size=config.eval_batch_size,
        latency_repeats=FLAGS.latency_repeats,
    )
    print(table)


if __name__ == "__main__":
    common.run(main)
