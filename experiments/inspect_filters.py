r"""Draws the filters the hypernetwork generates for test pairs, and relates them to motion.

    python -m experiments.inspect_filters --workdir=runs/demo [--num_pairs=8]

Writes <workdir>/filters/: one PNG per pair (the three generated banks as image grids),
similarity.json (global parameters, pairwise filter and motion similarities, and their
correlation) and prints how similar the filters of two pairs are against how similar
their relative motions are.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from absl import app, flags

from experiments import common

FLAGS = flags.FLAGS

flags.DEFINE_string("workdir", "runs/demo", "A trained global-local workdir.")
flags.DEFINE_string("split", "test", "Split the pairs come from.")
flags.DEFINE_integer("num_pairs", 8, "Pairs to inspect (the first N of the split).")
flags.DEFINE_integer("num_figures", 4, "Pairs whose filter banks are drawn.")
common.define_data_flags(default_dataset=None)
common.define_flow_source_flag()


def main(argv):
    del argv
    common.initialise()
    from gld.analysis import filter_inspection as inspect_lib
    from gld.evaluation import evaluate as evaluation
    from gld.runs import workdir as workdir_lib

    model, variables, config = workdir_lib.load_trained(FLAGS.workdir)
    if config.model != "global_local":
        raise app.UsageError(f"{FLAGS.workdir} holds a {config.model!r} model, not global_local")
    builder = common.prepare_dataset(FLAGS.dataset or config.dataset)
    source = common.data_source(builder, FLAGS.split)
    count = min(FLAGS.num_pairs, len(source))
    batch = next(
        evaluation.split_batches(
            source,
            batch_size=count,
            flow_source=FLAGS.flow_source or config.flow_source,
            max_examples=count,
            all_processes=False,
        )
    )
    inspected = inspect_lib.inspect_pairs(variables, batch, model)
    rotation, translation = inspected["rotation"], inspected["translation"]
    filter_sim, motion_sim = inspected["filter_similarity"], inspected["motion_similarity"]
    correlation = inspected["correlation"]

    out_dir = Path(FLAGS.workdir) / "filters"
    out_dir.mkdir(parents=True, exist_ok=True)
    ids = [str(i) for i in batch["id"]]
    for index in range(min(FLAGS.num_figures, count)):
        angle = float(np.degrees(np.arccos(np.clip((np.trace(rotation[index]) - 1) / 2, -1, 1))))
        inspect_lib.draw_filter_banks(
            inspected["kernels"],
            index,
            out_dir / f"{ids[index].replace('/', '_')}.png",
            title=f"{ids[index]}: rotation {angle:.1f} deg, t = {np.round(translation[index], 2)}",
        )
    (out_dir / "similarity.json").write_text(
        json.dumps(
            {
                "ids": ids,
                "global_params": inspected["global_params"].tolist(),
                "filter_similarity": filter_sim.tolist(),
                "motion_similarity": motion_sim.tolist(),
                "correlation": correlation,
            },
            indent=2,
        )
        + "\n"
    )
    print("pair A | pair B | filter similarity | motion similarity")
    upper = np.triu_indices(count, k=1)
    for a, b in zip(*upper, strict=True):
        print(f"{ids[a]} | {ids[b]} | {filter_sim[a, b]:+.3f} | {motion_sim[a, b]:+.3f}")
    print(
        f"correlation over {correlation['num_pairs']} pairs of pairs: "
        f"Pearson {correlation['pearson']:+.3f}, Spearman {correlation['spearman']:+.3f}"
    )
    print(f"wrote {out_dir}")


if __name__ == "__main__":
    common.run(main)
