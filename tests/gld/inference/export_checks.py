"""What the export tests share: a tiny global-local model and its inputs."""

import numpy as np
from conftest import TINY_MODEL, random_variables

from gld.models import registry

HEIGHT, WIDTH = 24, 32


def tiny_model():
    """(model, variables) of a tiny global-local model at HEIGHT x WIDTH."""
    model = registry.make_model("global_local", **TINY_MODEL)
    return model, random_variables(model, HEIGHT, WIDTH, seed=0)


def model_inputs(batch_size: int, seed: int = 0):
    """(image1, image2, flow) of a batch, seeded; images in [0, 1], as exported files take
    them (the network reads image - 0.5)."""
    rng = np.random.default_rng(seed)
    image1 = rng.uniform(0.0, 1.0, (batch_size, HEIGHT, WIDTH, 3)).astype(np.float32)
    image2 = rng.uniform(0.0, 1.0, (batch_size, HEIGHT, WIDTH, 3)).astype(np.float32)
    flow = rng.normal(0, 2, (batch_size, HEIGHT, WIDTH, 2)).astype(np.float32)
    return image1, image2, flow
