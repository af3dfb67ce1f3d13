r"""Trains a depth model and evaluates it: `python -m experiments.train [--flagfile=...]`.

With no flags this is the demo: it builds the embedded benchmark `gld_scenes/small` on
first use, trains the global-local model with ONE supervised pixel per image, evaluates
it with its references (the dataset mean, the per-pair oracle constant and sfm_flow, the
classical pipeline on the same flow) on the test split, prints the table and leaves
everything in runs/demo.
Re-running the same command resumes from the last checkpoint.

The final evaluation scores as `python -m experiments.evaluate --workdir=...` does by
default: a demon/* dataset by DeMoN's protocol, against the depth of the files its test
split was built from (--manual_dir, else where the build found them), into
<workdir>/eval_truth-file. When those files are not at hand at the end of the run, it is
scored at the records' resolution into <workdir>/eval rather than lost: one line and the
table's stamp say that it is not DeMoN's protocol and give the evaluate command that
scores it by DeMoN's protocol once the files are back.
"""

from __future__ import annotations

import shlex

from absl import flags

from experiments import common
from gld.runs import recipe

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "Run directory (checkpoints, logs, eval).")
flags.DEFINE_bool("final_eval", True, "Evaluate the final model on the whole test split.")
flags.DEFINE_integer("num_figures", 8, "Example figures written by the final evaluation.")
common.define_compile_cache_flag(
    "the final evaluation runs the periodic evaluation's program, and a relaunch or "
    "experiments.evaluate on the workdir compiles only what is new."
)
# The main job's recipe (gld.runs.recipe) gives the launcher's defaults. Paper flagfiles
# set the paper's (Adam 1e-4, constant, the paper's global module, no motion terms).
common.define_training_flags(**recipe.TRAINING)
common.define_architecture_flags(**recipe.ARCHITECTURE)
common.define_flow_net_flags()
common.define_data_flags()
common.define_distributed_flags()


def _given() -> set[str]:
    """The flags the command line (or a flagfile) gives."""
    return {name for name in FLAGS if FLAGS[name].present}


def main(argv):
    del argv
    common.initialise()
    import dataclasses

    from gld.inference import workdir_export
    from gld.runs import checkpoints
    from gld.training import trainer as train

    model_config, kept = recipe.with_stored_architecture(
        FLAGS.workdir, FLAGS.model, common.model_options(FLAGS.model), _given()
    )
    if kept:
        listed = ", ".join(f"{name}={value}" for name, value in sorted(kept.items()))
        print(f"{FLAGS.workdir} was trained with {listed}: kept (flags given override)")
    weights = {name: FLAGS[name].value for name in recipe.MOTION_WEIGHTS}
    model_config, weights = recipe.motion_where_it_applies(
        FLAGS.model, model_config, weights, _given()
    )
    # Every option is checked before the dataset is built or the workdir touched.
    warmup_steps = recipe.warmup_that_fits(FLAGS.steps, FLAGS.warmup_steps, _given())
    if warmup_steps != FLAGS.warmup_steps:
        print(f"--steps={FLAGS.steps}: {warmup_steps} warm-up steps (the recipe's 5%)")
        FLAGS.warmup_steps = warmup_steps  # flags.txt relaunches the run as it trained
    run_config = common.train_config(
        model_config=model_config,
        dataset=FLAGS.dataset,
        warmup_steps=warmup_steps,
        **weights,
    )
    evaluates = FLAGS.final_eval or run_config.eval_every > 0
    builder, height, width, train_source, test_source = common.training_data(evaluates)
    run_config = dataclasses.replace(run_config, height=height, width=width)
    trained_before = checkpoints.last_checkpointed_step(FLAGS.workdir)
    state = train.train_and_evaluate(
        run_config,
        FLAGS.workdir,
        train_source,
        test_source,
        records={
            "flags.txt": common.flags_file_text(),
            workdir_export.FLOW_RECORD: common.dataset_flow_record(builder),
        },
        keep_compiled=FLAGS.compile_cache,
    )
    step = int(state.step)
    if FLAGS.final_eval:
        from data.demon import file_truth
        from gld.evaluation import evaluation_run

        done = evaluation_run.final_evaluation_of(FLAGS.workdir, FLAGS.dataset, step)
        if done is not None and step == trained_before:
            print(
                f"{done / 'metrics.json'} already scores step {step}: not evaluated again "
                f"(python -m experiments.evaluate --workdir={FLAGS.workdir} does it again)"
            )
            return
        evaluation_run.evaluate_split(
            FLAGS.workdir,
            prepare_dataset=lambda _: builder,
            open_file_truth=file_truth.for_split,
            dataset=FLAGS.dataset,
            manual_dir=FLAGS.manual_dir,
            num_figures=FLAGS.num_figures,
            batch_size=run_config.eval_batch_size,
            rescore_command=_rescore_command(),
        )


def _rescore_command() -> str:
    """The command that scores the trained run by DeMoN's protocol once its DeMoN files
    are back (the final evaluation's fallback names it)."""
    words = ["python", "-m", "experiments.evaluate", f"--workdir={FLAGS.workdir}"]
    if FLAGS.data_dir:
        words.append(f"--data_dir={FLAGS.data_dir}")
    command = shlex.join(words)
    return f"{command} --manual_dir=<the folder of the DeMoN files>"


if __name__ == "__main__":
    common.run(main)
