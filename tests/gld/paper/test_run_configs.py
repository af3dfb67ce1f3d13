"""A suite's runs as training configurations: every one validates, with the suite's
budget, optimiser and schedule."""

import pytest

from gld.paper import suite as paper_suite
from gld.paper.run_configs import run_config
from gld.paper.scales import LARGE_MODELS, SUITES


@pytest.mark.parametrize("suite", sorted(SUITES))
def test_every_run_validates_with_the_suites_budget_and_optimiser(suite):
    scale = SUITES[suite]
    runs = paper_suite.suite_runs(scale)
    assert len({run.name for run in runs}) == len(runs)
    for run in runs:
        config = run_config(scale, run, height=48, width=64)
        large = run.model in LARGE_MODELS
        assert config.steps == (scale.large_steps if large else scale.steps), run.name
        # The same optimiser, rate, schedule, batch and seed for every learned model (the
        # learning-rate check's runs and the flow experiment at the check's rate).
        checked = run.name.endswith("_low_lr") or run.name in paper_suite.FLOW_EXPERIMENT
        rate = scale.check_learning_rate if checked else scale.learning_rate
        assert (config.learning_rate, config.lr_schedule, config.batch_size, config.seed) == (
            rate,
            "cosine",
            scale.batch_size,
            0,
        )
        assert config.warmup_steps == max(1, round(config.steps * scale.warmup_fraction))
        # Only the runs of the over-fitting figure are evaluated during training.
        assert config.eval_examples == (scale.curve_examples if run.curve else 0)
        assert bool(config.eval_every) == run.curve
        assert config.dataset == (scale.varying_dataset if run.varying else scale.dataset)
        if run.model != "global_local":
            assert config.epipolar_weight == 0
        if run.model not in ("global_local", *paper_suite.FLOW_NET_MODELS):
            assert config.model_config == {}, run.name
