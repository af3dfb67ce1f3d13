"""The optimiser and its learning-rate schedules."""

import numpy as np
import pytest

from gld.runs import optimizer as optimizer_lib


def test_learning_rate_schedules():
    constant = optimizer_lib.learning_rate_schedule(1e-4, "constant")
    assert float(constant(0)) == float(constant(10_000)) == pytest.approx(1e-4)
    warmed = optimizer_lib.learning_rate_schedule(1e-4, "constant", warmup_steps=100)
    assert float(warmed(0)) == 0.0
    assert float(warmed(50)) == pytest.approx(5e-5)
    assert float(warmed(100)) == float(warmed(10_000)) == pytest.approx(1e-4)
    cosine = optimizer_lib.learning_rate_schedule(1e-3, "cosine", steps=1000, warmup_steps=100)
    assert float(cosine(0)) == 0.0
    assert float(cosine(50)) == pytest.approx(5e-4)
    assert float(cosine(100)) == pytest.approx(1e-3)
    assert float(cosine(550)) == pytest.approx(0.5 * (1e-3 + 1e-5), rel=1e-3)
    assert float(cosine(1000)) == pytest.approx(1e-5)
    with pytest.raises(ValueError, match="warmup_steps \\(100\\) must be in"):
        optimizer_lib.learning_rate_schedule(1e-3, "cosine", steps=100, warmup_steps=100)
    with pytest.raises(ValueError, match="lr_schedule"):
        optimizer_lib.learning_rate_schedule(1e-3, "step")


def test_the_optimiser_follows_the_schedule_and_logs_it():
    optimizer = optimizer_lib.make_optimizer(1e-3, "cosine", steps=10, warmup_steps=2)
    params = {"w": np.ones(3, np.float32)}
    opt_state = optimizer.init(params)
    rates = []
    for _ in range(4):
        _, opt_state = optimizer.update({"w": np.ones(3, np.float32)}, opt_state, params)
        rates.append(float(opt_state.hyperparams["learning_rate"]))
    # inject_hyperparams records the rate of the step just taken: 0 (warm-up start), 5e-4, 1e-3.
    assert rates[:3] == pytest.approx([0.0, 5e-4, 1e-3])
    assert rates[3] < 1e-3


def test_toward_start_pulls_the_parameters_back_to_their_starting_values():
    optimizer = optimizer_lib.toward_start(0.1)
    start = {"w": np.array([1.0, -2.0], np.float32)}
    opt_state = optimizer.init(start)
    params = {"w": np.array([3.0, -2.0], np.float32)}
    updates, _ = optimizer.update({"w": np.zeros(2, np.float32)}, opt_state, params)
    # A tenth of the distance back, only where the parameter has moved.
    np.testing.assert_allclose(updates["w"], [-0.2, 0.0])
    # The starting values are a copy: moving the params in place does not move them.
    start["w"][0] = 5.0
    updates, _ = optimizer.update({"w": np.ones(2, np.float32)}, opt_state, params)
    np.testing.assert_allclose(updates["w"], [0.8, 1.0])
    with pytest.raises(ValueError, match="parameters"):
        optimizer.update({"w": np.zeros(2, np.float32)}, opt_state)
