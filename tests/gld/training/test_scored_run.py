"""`gld.training.scored_run`: a run trained once (a finished run reused, an unfinished one
resumed), and scored."""

import numpy as np
from conftest import tiny_train_config

from gld.evaluation import evaluate as evaluation
from gld.models import registry
from gld.runs import workdir as workdir_lib
from gld.training import scored_run


def _fake_trainer(monkeypatch, calls):
    """Records each training and leaves a checkpoint of the config's last step."""

    def train_and_evaluate(config, workdir, train_source, test_source, **options):
        calls.append((config.steps, train_source, test_source, options["progress"]))
        (workdir / "checkpoints" / str(config.steps)).mkdir(parents=True, exist_ok=True)

    monkeypatch.setattr(scored_run.trainer, "train_and_evaluate", train_and_evaluate)


def test_a_run_is_trained_until_it_finishes_then_reused(tmp_path, monkeypatch):
    calls, messages = [], []
    _fake_trainer(monkeypatch, calls)
    config = tiny_train_config(steps=4)
    run_dir = tmp_path / "run"
    (run_dir / "checkpoints" / "2").mkdir(parents=True)  # an unfinished run: resumed

    seconds = scored_run.train_unless_finished(
        "tiny", config, run_dir, "train", "test", progress=False, print_fn=messages.append
    )
    assert seconds is not None and seconds >= 0
    assert calls == [(4, "train", "test", False)]
    assert messages == [f"tiny: training 4 steps in {run_dir}"]

    again = scored_run.train_unless_finished(
        "tiny", config, run_dir, "train", print_fn=messages.append
    )
    # Reused: no time trained, but through the trainer, which checks the stored config
    # against this one and verifies the checkpoint (training no step when it is intact).
    assert again is None and len(calls) == 2
    assert messages[-1] == f"tiny: reusing the finished run in {run_dir} (step 4)"


def test_a_run_is_scored_as_the_evaluation_loop_scores_it(tiny_scenes, trained_workdir):
    source = tiny_scenes.as_data_source("test")
    scored = scored_run.score(trained_workdir, source, max_examples=4)
    model, variables, config = workdir_lib.load_trained(trained_workdir)
    assert scored.config == config
    assert scored.parameters == registry.parameter_counts(variables["params"])["total"] > 0
    # The run's own evaluation batch and flow by default.
    expected, _ = evaluation.evaluate_source(
        model,
        variables,
        source,
        batch_size=config.eval_batch_size,
        flow_source=config.flow_source,
        max_examples=4,
    )
    assert np.asarray(scored.per_example["example_mask"]).sum() == 4
    np.testing.assert_allclose(scored.per_example["abs_inv"], expected["abs_inv"], rtol=1e-6)
    # Another flow gives other scores: the option reaches the evaluation.
    with_gt_flow = scored_run.score(trained_workdir, source, flow_source="gt", max_examples=4)
    assert config.flow_source != "gt"
    assert not np.allclose(with_gt_flow.per_example["abs_inv"], expected["abs_inv"])
