r"""The paper's experimental section on the embedded benchmark, one command:

    python -m experiments.paper --suite=cpu          # gld_scenes/small, 128x96, ~3 h on 2 cores
    python -m experiments.paper --suite=cpu_full     # twice the budget, every run: ~11 h
    python -m experiments.paper --suite=paper        # gld_scenes/full, 256x192, 94K steps (GPU)
    python -m experiments.paper --suite=cpu --only=train/global_local_1px,classical
    python -m experiments.paper --suite=cpu --report_only

Trains and evaluates every run of the suite (`gld.paper.suite`) in <workdir>/runs/, with
the analyses, each as soon as the runs it reads have finished (pose probe, triangulation
with the probe's pose, flow-error curves, qualitative predictions, generated filters),
and writes the report (every table with the
paper's numbers beside ours, the targets checked, the figures as PNG) to <report_dir>.
Each finished task leaves a result in <results_dir> (default <report_dir>/results/, kept
with the report) and is reused; an unfinished training run resumes from its last
checkpoint, so a killed suite, re-run with the same command, continues where it stopped.
The results alone are enough to continue in another checkout: an analysis retrains (same
seed) a run whose checkpoint is not in <workdir> and notes it if it does not score its
result. Before each task the suite prints which it is and the ETA of the rest; each
training run shows its own progress bar.

Multi-process (the paper suite on several hosts): the same command on every host with
`--num_processes=N --process_id=i --coordinator_address=host0:port`; process 0 writes
the results and the report.
"""

from __future__ import annotations

from pathlib import Path

from absl import app, flags

from experiments import common
from gld.paper import scales as paper_scales

FLAGS = flags.FLAGS

flags.DEFINE_enum(
    "suite", "cpu", list(paper_scales.SUITES), "Which scale to run (gld.paper.scales.SUITES)."
)
flags.DEFINE_string("workdir", None, "The training runs (default: runs/paper_<suite>).")
flags.DEFINE_string(
    "report_dir", None, "Where the report goes (default: report/ for cpu, report/<suite>/ else)."
)
flags.DEFINE_string(
    "results_dir",
    None,
    "Each task's result, from which the report is written and the suite continues "
    "(default: <report_dir>/results).",
)
flags.DEFINE_list("only", None, "Run only these tasks (names or prefixes: train/, classical).")
flags.DEFINE_bool("report_only", False, "Write the report from the finished results only.")
flags.DEFINE_bool("progress", True, "Progress bars of the training runs.")
common.define_compile_cache_flag(
    "the suite's runs of one program (a model at several label densities, say) compile "
    "it once, and a continued suite reuses what the killed one compiled."
)
flags.DEFINE_string("data_dir", None, "Where built datasets live (default: ./datasets).")
flags.DEFINE_string("manual_dir", None, "Unused by gld_scenes; kept for the data flags.")
common.define_distributed_flags()


def main(argv):
    del argv
    common.initialise()
    import jax

    from data.gld_scenes import redraw
    from gld.arguments import ArgumentError
    from gld.paper import discussion as paper_discussion
    from gld.paper import report as paper_report
    from gld.paper import runner as paper_runner
    from gld.paper import training_runs as paper_training_runs
    from gld.paper.report_results import ReportResults
    from gld.runs import workdir as workdir_lib

    scale = paper_scales.SUITES[FLAGS.suite]
    workdir = Path(FLAGS.workdir or f"runs/paper_{scale.name}")
    if FLAGS.compile_cache:
        workdir_lib.keep_compiled_programs(workdir)
    report_dir = Path(
        FLAGS.report_dir or ("report" if scale.name == "cpu" else f"report/{scale.name}")
    )

    def data(dataset: str) -> paper_training_runs.Data:
        # Built between runs, after JAX has started: in this process.
        builder = common.prepare_dataset(dataset, parallel=False)
        height, width = common.dataset_resolution(builder)
        return paper_training_runs.Data(
            name=builder.info.full_name,
            train=common.data_source(builder, "train"),
            test=common.data_source(builder, "test"),
            height=height,
            width=width,
            texture=redraw.texture_reader(builder),
        )

    results_dir = Path(FLAGS.results_dir or report_dir / "results")
    import data as datasets

    runner = paper_runner.SuiteRunner(
        scale,
        workdir,
        data,
        results_dir=results_dir,
        progress=FLAGS.progress,
        dataset_version=datasets.version,
    )
    try:
        runner.selected(FLAGS.only)
    except ValueError as error:
        raise app.UsageError(f"--only: {error}") from None
    # The hand-written discussion is checked before any task runs: a number written by
    # hand or an unknown placeholder in it would otherwise stop the report at the end.
    try:
        paper_discussion.report_discussion(
            ReportResults(scale, runner.finished(), results_dir), report_dir
        )
    except ValueError as error:
        raise ArgumentError(str(error)) from None
    commit = common.commit_stamp(report_dir, results_dir)
    failures = [] if FLAGS.report_only else runner.run(FLAGS.only, commit=commit)
    if jax.process_index() == 0:
        path = paper_report.write_report(
            scale,
            runner.finished(),
            results_dir,
            report_dir,
            commit=commit,
            command=f"python -m experiments.paper --suite={scale.name}",
        )
        print(f"wrote {path}")
    if failures:
        raise SystemExit(
            "failed tasks (the others finished; re-run to retry):\n" + "\n".join(failures)
        )


if __name__ == "__main__":
    common.run(main)
