"""The offline reference of an online run: the same frames and gradient steps, shuffled.

    result = offline_reference(stream, make_learner, frames=1500, updates=1480,
                               online_variables=online_learner.published)

The pairs the stream's first `frames` frames give (their range readings as labels, made
as the online learner makes them) are all kept; `updates` Adam steps then run on batches
drawn uniformly from all of them, with the online run's batch size, zoom and learning
rate; and the trained model, frozen, predicts every frame again and is scored
(`score_frozen`). Given the online run's final model, that one is scored on the same
frames the same way: the two trained models compare at equal gradient steps, each
seeing every frame after training (the online run's prequential curve, in contrast,
scores each frame before the learner has trained on it).
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import numpy as np

from gld.online.learner import OnlineLearner
from gld.online.stream import FrameStream


def score_frozen(learner: OnlineLearner, stream: FrameStream, frames: int) -> dict[str, float]:
    """Mean Abs-Inv and x mean of `learner`'s model, frozen, over the stream's first
    `frames` frames."""
    if learner.settings.learn:
        raise ValueError("score_frozen takes a learner with learn=False")
    rows = [learner.observe(frame) for frame in itertools.islice(stream.frames(), frames)]
    scored = [row for row in rows if "abs_inv" in row]
    if not scored:
        raise ValueError(f"none of the first {frames} frames was scored (no truth or no partner)")
    error = float(np.mean([row["abs_inv"] for row in scored]))
    reference = float(np.mean([row["abs_inv_mean"] for row in scored]))
    return {"abs_inv": error, "abs_inv_mean": reference, "x_mean": error / reference}


def offline_reference(
    stream: FrameStream,
    make_learner: Callable[..., OnlineLearner],
    *,
    frames: int,
    updates: int,
    online_variables: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The offline reference (module docstring).

    Args:
      stream: the online run's stream.
      make_learner: makes a learner of the run's model and settings; its keyword
        arguments replace settings (`learn`, `capacity`, `asynchronous`) or give the
        starting `variables`.
      frames: the frames the online run saw.
      updates: its gradient steps.
      online_variables: the online run's final model, scored alike when given.

    Returns:
      {"frames", "updates", "pairs", "offline": score, and "online": score}.
    """
    collector = make_learner(learn=False, capacity=frames, asynchronous=False)
    for frame in itertools.islice(stream.frames(), frames):
        collector.observe(frame, predict=False)
    trainer = make_learner(learn=True, capacity=frames, asynchronous=False)
    trainer.buffer = collector.buffer
    trainer.train_offline(updates)
    result = {"frames": frames, "updates": trainer.updates, "pairs": len(collector.buffer)}
    result["offline"] = score_frozen(
        make_learner(learn=False, variables=trainer.published), stream, frames
    )
    if online_variables is not None:
        result["online"] = score_frozen(
            make_learner(learn=False, variables=online_variables), stream, frames
        )
    return result
