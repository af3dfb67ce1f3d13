"""The network of a model exported by `python -m experiments.export`, with only JAX and numpy.

    from gld.inference.deploy import DeployedModel
    model = DeployedModel.load("runs/demo/model.gldx")
    depth = model(image1, image2, flow)        # [B, H, W] (or [H, W] for one pair)
    outputs = model.predict(image1, image2, flow)   # + inv_depth, global_params
    depth = model(image1, image2, flow, intrinsics1=k, intrinsics2=k)  # model.extra_inputs

This is the network alone, at its resolution, given the flow; from two frames of any
size to metric depth, the flow computed inside, is `gld.inference.runtime.DepthRuntime`.
This module imports nothing but JAX, numpy and the standard library (not flax, optax,
orbax, TFDS, grain, OpenCV, nor any gld module that does); `jax.export`'s
deserialisation also needs the small `flatbuffers` package.

Inputs are at the exported resolution (`model.height` x `model.width`, the training
resolution; nothing is resized here): images uint8 [0, 255] or float32 in [0, 1]
(uint8 / 255; a float outside [0, 1] is refused), [B, H, W, 3] or one pair [H, W, 3];
flow float32 pixels, image1 -> image2, [B, H, W, 2] or [H, W, 2]. A model trained to
read more (`extra_inputs`: the odometry's relative pose, the flow's essential-matrix
pose, the cameras, normalised at the exported resolution, for a model that reads a pose
against the flow, or a given pose and then the cameras) takes them by keyword, float32,
with or without the batch axis as the images; the metadata's "inputs" say what each is.
Depth is in units of the pair's baseline (the distance between the camera centres):
metric depth = depth * baseline.
"""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path
from typing import Any

import jax
import numpy as np

# The file layout written by gld.inference.export (kept in step with it; this module may
# not import it).
FORMAT = "gld-exported-model"
FORMAT_VERSION = 3
# version 1: no extra inputs; 1 and 2: the exported function takes images in [-0.5, 0.5]
READABLE_VERSIONS = (1, 2, 3)
METADATA_MEMBER = "metadata.json"
EXPORTED_MEMBER = "model.jaxexport"
WEIGHTS_MEMBER = "weights.npz"
FLOW_EXPORTED_MEMBER = "flow_net.jaxexport"
FLOW_WEIGHTS_MEMBER = "flow_net_weights.npz"


def current_platform() -> str:
    """The platform JAX runs on here, named as `jax.export` names it (cpu, cuda, rocm, tpu)."""
    backend = jax.default_backend()
    if backend != "gpu":
        return backend
    version = getattr(jax.devices()[0].client, "platform_version", "").lower()
    return "rocm" if "rocm" in version else "cuda"


def _read_archive(path: Path) -> tuple[dict[str, Any], dict[str, bytes]]:
    if not path.is_file():
        raise FileNotFoundError(f"exported model {path} not found")
    if not zipfile.is_zipfile(path):
        raise ValueError(f"{path} is not an exported gld model (not a zip archive)")
    with zipfile.ZipFile(path) as archive:
        missing = sorted(
            {METADATA_MEMBER, EXPORTED_MEMBER, WEIGHTS_MEMBER} - set(archive.namelist())
        )
        if missing:
            raise ValueError(f"{path} is not an exported gld model: it lacks {missing}")
        metadata = json.loads(archive.read(METADATA_MEMBER))
        members = {name: archive.read(name) for name in archive.namelist()}
    if metadata.get("format") != FORMAT:
        raise ValueError(f"{path}: format {metadata.get('format')!r} is not {FORMAT!r}")
    if metadata.get("format_version") not in READABLE_VERSIONS:
        raise ValueError(
            f"{path} has format version {metadata.get('format_version')}; this "
            "gld.inference.deploy "
            f"reads versions {list(READABLE_VERSIONS)}: export the model again with this gld"
        )
    if metadata.get("flow", {}).get("estimator") == "flow_net":
        missing = sorted({FLOW_EXPORTED_MEMBER, FLOW_WEIGHTS_MEMBER} - set(members))
        if missing:
            raise ValueError(f"{path} records a flow network's flow but lacks {missing}")
    return metadata, members


def _deserialised(path: Path, serialized: bytes) -> jax.export.Exported:
    """The exported function, checked to run on this platform."""
    exported = jax.export.deserialize(bytearray(serialized))
    platform = current_platform()
    if platform not in exported.platforms:
        raise ValueError(
            f"{path} was exported for {list(exported.platforms)}, but JAX runs on "
            f"{platform!r} here: export it again with --platforms including {platform}"
        )
    return exported


def _weights(stored_bytes: bytes) -> list[np.ndarray]:
    with np.load(io.BytesIO(stored_bytes), allow_pickle=False) as stored:
        return [stored[f"{index:05d}"] for index in range(len(stored.files))]


def _as_unit_image(image: np.ndarray, name: str) -> np.ndarray:
    """uint8 or float32 [B, H, W, 3] -> float32 in [0, 1]; a float outside it is refused."""
    if image.dtype == np.uint8:
        return image.astype(np.float32) / np.float32(255.0)
    if image.dtype != np.float32:
        raise ValueError(f"{name} must be uint8 or float32, got dtype {image.dtype}")
    if not np.all(np.isfinite(image)):
        raise ValueError(f"{name} contains NaN or inf")
    low, high = float(image.min()), float(image.max())
    if low < 0.0 or high > 1.0:
        raise ValueError(
            f"float32 {name} must lie in [0, 1] (uint8 / 255), got [{low:.3g}, {high:.3g}]"
        )
    return image


class DeployedFlowNetwork:
    """The flow network exported beside a model trained on its flow: two image batches
    [B, H, W, 3] (uint8 or float32 in [0, 1]) at the exported resolution -> flow
    [B, H, W, 2] float32 pixels, image1 -> image2."""

    def __init__(self, exported: jax.export.Exported, weights: list[np.ndarray]):
        self._weights = jax.device_put(weights)
        self._call = jax.jit(exported.call)

    def __call__(self, image1: np.ndarray, image2: np.ndarray) -> np.ndarray:
        first = _as_unit_image(np.asarray(image1), "image1")
        second = _as_unit_image(np.asarray(image2), "image2")
        return np.asarray(jax.device_get(self._call(self._weights, first, second)))


class DeployedModel:
    """An exported depth model: the deserialised forward pass and its weights.

    Attributes:
      metadata: the file's metadata.json (inputs, outputs, units, model, source run).
      height, width: the image size the model takes (its training resolution).
      batch_size: the fixed batch size, or None when any batch size is accepted.
      platforms: the platforms the file was lowered for.
      extra_inputs: what the model reads by keyword besides the images and flow, in the
        exported order (empty for most models).
      flow: how its input flow is computed from the frames (metadata "flow": {"estimator":
        "dis" and OpenCV's settings, "flow_net", or "model" for a model that estimates
        its own}); files of version 1 and 2 do not record it.
      flow_network: the exported flow network of a "flow_net" flow, else None.
    """

    def __init__(
        self,
        metadata: dict[str, Any],
        exported: jax.export.Exported,
        weights: list,
        flow_network: DeployedFlowNetwork | None = None,
    ):
        self.metadata = metadata
        self.height, self.width = int(metadata["height"]), int(metadata["width"])
        self.batch_size = metadata["batch_size"]
        self.platforms = tuple(exported.platforms)
        self.extra_inputs = tuple(metadata.get("extra_inputs", ()))
        self.flow = metadata.get("flow")
        self.flow_network = flow_network
        # Before version 3 the exported function took images in [-0.5, 0.5].
        self._image_offset = np.float32(0.5 if metadata["format_version"] < 3 else 0.0)
        # Each extra input's metadata entry (shape with its batch axis, help), checked by load.
        described = {entry["name"]: entry for entry in metadata.get("inputs", ())}
        self._extra_entries = {key: described[key] for key in self.extra_inputs}
        self._exported = exported
        # On the device once: each call passes only the images and the flow.
        self._weights = jax.device_put(weights)
        self._call = jax.jit(exported.call)

    @classmethod
    def load(cls, path: str | Path) -> DeployedModel:
        """Reads a file written by `gld.inference.export` and checks that it runs here."""
        path = Path(path)
        metadata, members = _read_archive(path)
        exported = _deserialised(path, members[EXPORTED_MEMBER])
        weights = _weights(members[WEIGHTS_MEMBER])
        expected = metadata["weights"]
        avals = exported.in_avals[: len(expected)]
        inputs = 3 + len(metadata.get("extra_inputs", ()))
        described = {entry.get("name") for entry in metadata.get("inputs", ())}
        undescribed = [key for key in metadata.get("extra_inputs", ()) if key not in described]
        if undescribed:
            raise ValueError(f"{path}: the metadata lists no shape for inputs {undescribed}")
        if len(weights) != len(expected) or len(exported.in_avals) != len(expected) + inputs:
            raise ValueError(
                f"{path}: {len(weights)} stored weights, {len(expected)} listed in the "
                f"metadata and {len(exported.in_avals) - inputs} taken by the model"
            )
        for weight, entry, aval in zip(weights, expected, avals, strict=True):
            if list(weight.shape) != entry["shape"] or weight.shape != aval.shape:
                raise ValueError(
                    f"{path}: weight {entry['name']} has shape {weight.shape}, the model "
                    f"takes {aval.shape}"
                )
            if weight.dtype != aval.dtype:
                raise ValueError(
                    f"{path}: weight {entry['name']} has dtype {weight.dtype}, the model "
                    f"takes {aval.dtype}"
                )
        flow_network = None
        if FLOW_EXPORTED_MEMBER in members:
            flow_network = DeployedFlowNetwork(
                _deserialised(path, members[FLOW_EXPORTED_MEMBER]),
                _weights(members[FLOW_WEIGHTS_MEMBER]),
            )
        return cls(metadata, exported, weights, flow_network)

    def _check_batch(self, array: np.ndarray, name: str, channels: int) -> np.ndarray:
        size = f"{self.height}, {self.width}, {channels}"
        expected = f"[B, {size}] or [{size}]"
        if array.ndim not in (3, 4) or array.shape[-3:] != (self.height, self.width, channels):
            raise ValueError(
                f"{name} must be {expected} (the exported resolution), got shape {array.shape}"
            )
        return array if array.ndim == 4 else array[None]

    def _as_model_image(self, image: np.ndarray, name: str) -> np.ndarray:
        image = self._check_batch(np.asarray(image), name, 3)
        return _as_unit_image(image, name) - self._image_offset

    def _extra(self, given: dict[str, Any], batch_size: int, single: bool) -> list[np.ndarray]:
        """The extra inputs in the exported order, checked, with a batch axis."""
        unexpected = sorted(set(given) - set(self.extra_inputs))
        if unexpected:
            reads = list(self.extra_inputs) or "only the images and flow"
            raise ValueError(f"this model does not read {unexpected}; it reads {reads}")
        missing = [key for key in self.extra_inputs if key not in given]
        if missing:
            needs = "; ".join(
                f"{key}: {self._extra_entries[key].get('help', '')}" for key in missing
            )
            raise ValueError(f"this model also reads {missing}: give them by keyword ({needs})")
        arrays = []
        for key in self.extra_inputs:
            shape = tuple(self._extra_entries[key]["shape"][1:])
            value = np.asarray(given[key])
            if value.dtype.kind not in "fiu":
                raise ValueError(f"{key} must be numeric, got dtype {value.dtype}")
            value = value.astype(np.float32)
            if single:
                value = value[None]
            if value.shape != (batch_size, *shape):
                dims = ", ".join(map(str, shape if single else ("B", *shape)))
                raise ValueError(
                    f"{key} must be [{dims}] with these images, got shape {np.shape(given[key])}"
                )
            if not np.all(np.isfinite(value)):
                raise ValueError(f"{key} contains NaN or inf")
            arrays.append(value)
        return arrays

    def predict(
        self, image1: np.ndarray, image2: np.ndarray, flow: np.ndarray, **extra: Any
    ) -> dict[str, np.ndarray]:
        """Every output of the exported model, as numpy.

        Args:
          image1, image2: [B, H, W, 3] or [H, W, 3], uint8 or float32 in [0, 1].
          flow: [B, H, W, 2] or [H, W, 2] float32, pixels, image1 -> image2.
          **extra: the inputs `extra_inputs` names (rotation [3, 3], translation [3],
            intrinsics1 [4], ...; [B, ...] with a batch), float32.

        Returns:
          {"inv_depth": [B, H, W], "depth": [B, H, W] in baselines, and the model's
          other outputs (the global-local model's "global_params" [B, 6])}; without the
          batch axis when the inputs have none.
        """
        ranks = {"image1": np.ndim(image1), "image2": np.ndim(image2), "flow": np.ndim(flow)}
        if len(set(ranks.values())) != 1:
            raise ValueError(f"image1, image2 and flow must all have a batch axis or none: {ranks}")
        single = ranks["image1"] == 3
        first = self._as_model_image(image1, "image1")
        second = self._as_model_image(image2, "image2")
        flow = self._check_batch(np.asarray(flow), "flow", 2)
        if flow.dtype != np.float32:
            raise ValueError(f"flow must be float32 pixels, got dtype {flow.dtype}")
        if not np.all(np.isfinite(flow)):
            raise ValueError("flow contains NaN or inf")
        if not first.shape[0] == second.shape[0] == flow.shape[0]:
            raise ValueError(
                f"image1, image2 and flow must have the same batch size, got "
                f"{first.shape[0]}, {second.shape[0]} and {flow.shape[0]}"
            )
        if self.batch_size is not None and first.shape[0] != self.batch_size:
            raise ValueError(
                f"this model was exported for batch size {self.batch_size}, got "
                f"{first.shape[0]}: export it again with a symbolic batch (no --batch_size)"
            )
        given = self._extra(extra, first.shape[0], single)
        outputs = jax.device_get(self._call(self._weights, first, second, flow, *given))
        outputs = {key: np.asarray(value) for key, value in outputs.items()}
        if single:
            outputs = {key: value[0] for key, value in outputs.items()}
        return outputs

    def __call__(
        self, image1: np.ndarray, image2: np.ndarray, flow: np.ndarray, **extra: Any
    ) -> np.ndarray:
        """Depth of view 1 in baselines: [B, H, W], or [H, W] for one pair; `extra` as
        for `predict`."""
        return self.predict(image1, image2, flow, **extra)["depth"]
