"""The learning-rate check: a collapse read from the logged gradient norms, and the run
each comparison uses."""

from gld.paper.rate_check import collapse, compared_run
from gld.paper.scales import SUITES


def _result(losses, grad_norms):
    steps = range(50, 50 * (len(losses) + 1), 50)
    return {
        "curves": {
            "train": [],
            "loss": [[s, v] for s, v in zip(steps, losses, strict=True)],
            "grad_norm": [[s, v] for s, v in zip(steps, grad_norms, strict=True)],
        }
    }


def test_a_gradient_that_vanishes_against_its_own_scale_is_a_collapse():
    # A small network's gradient: 1e-2 at first, then 1e-7 (never exactly zero).
    vanished = _result([0.14] * 8, [7e-3, 6e-3, 2e-3, 1e-6, 5e-7, 4e-7, 6e-7, 3e-7])
    assert collapse(vanished) == (200, 5, 8)
    # Out of view with a rare batch back in view: the gradient flickers up, still collapsed.
    flickering = _result([0.14] * 8, [1e-2, 2.6e-2, 4e-3, 1.5e-5, 1.5e-3, 2e-5, 1.3e-5, 1.2e-5])
    assert collapse(flickering) == (200, 4, 8)
    # A gradient that spikes, then vanishes: it collapsed after the spike, not at the
    # first step, which is small against the spike but learning.
    spiked = _result([0.14] * 8, [0.2, 0.3, 300.0, 5.0, 1e-4, 1e-4, 1e-4, 1e-4])
    assert collapse(spiked) == (250, 6, 8)
    # Vanished, then one batch spikes it: the collapse began before the spike.
    relapsed = _result([0.14] * 8, [0.5, 0.4, 0.0, 0.0, 4.7, 0.0, 0.0, 0.0])
    assert collapse(relapsed) == (150, 5, 8)
    # 2e-3 of the largest norm at the end is not yet vanished.
    slow = _result([0.14] * 8, [1.0, 0.5, 0.1, 0.05, 2e-3, 2e-3, 2e-3, 2e-3])
    assert collapse(slow) is None
    # Small but alive: 2% of the largest norm at the end.
    alive = _result([0.14] * 8, [0.5, 0.3, 0.1, 0.05, 0.02, 0.01, 0.01, 0.01])
    assert collapse(alive) is None
    # One vanished record in eight is a blip, not a collapse.
    blip = _result([0.14] * 8, [0.5, 0.3, 0.0, 0.05, 0.02, 0.01, 0.01, 0.01])
    assert collapse(blip) is None


def test_the_rate_check_never_prefers_a_collapsed_run():
    scale = SUITES["cpu"]
    # Self-supervised at the suite's rate: everything projects out of view, the
    # photometric loss is low and the gradient has vanished.
    collapsed = _result([0.14] * 8, [7e-3, 6e-3, 1e-6, 5e-7, 4e-7, 6e-7, 3e-7, 2e-7])
    learning = _result([0.20] * 8, [0.5, 0.4, 0.3, 0.3, 0.2, 0.2, 0.2, 0.2])
    results = {"struct2depth": collapsed, "struct2depth_low_lr": learning}
    assert compared_run(scale, "struct2depth", results.get) == "struct2depth_low_lr"
    # Neither collapsed: the lower training loss.
    results["struct2depth"] = _result([0.14] * 8, [0.5] * 8)
    assert compared_run(scale, "struct2depth", results.get) == "struct2depth"
    # Both collapsed: the lower training loss too (the report marks both).
    results = {"struct2depth": collapsed, "struct2depth_low_lr": collapsed}
    assert compared_run(scale, "struct2depth", results.get) == "struct2depth"
    assert compared_run(scale, "struct2depth", {}.get) is None
