"""The global-local model F(I1, I2, w): global encoder -> hypernetwork -> local network.

The global module sees the image pair and the flow and emits a 6-vector of global
parameters; a linear layer turns it into three 3x3 filter banks (20, 10, 20 output
channels); those banks, applied per example to [flow, x, y], and a final shared 3x3
conv produce the inverse depth. The paper's numbers are the defaults, and each
ablation of the paper's Table (image pair, CoordConv, global module, flow) is a switch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from gld import geometry, pose_refinement
from gld.flow_pose import FLOW_POSE_KEYS
from gld.models import layers
from gld.models.filter_banks import FORMULATIONS, SharedConv, apply_filter_banks
from gld.models.global_encoder import ENCODER_NORMS, GlobalEncoder
from gld.models.global_pose import (  # noqa: F401  (POSE_ROTATION_SCALE: read as model.POSE_ROTATION_SCALE)
    POSE_ROTATION_SCALE,
    _unit,
    global_params_pose,
    pose_parameters,
)
from gld.models.hypernet import MODULATION_SCALE, HyperNetwork, StaticFilterBanks
from gld.models.parallax import parallax_flow, parallax_inverse_depth
from gld.options import option

LOCAL_FLOW_UNITS = ("normalised", "pixels")
GLOBAL_NORMS = ("none", "batch")
# What the local network sees beyond the image (`GlobalLocal.border`).
BORDERS = ("zero", "edge")
GLOBAL_SOURCES = ("encoder", "pose", "flow_pose")
# The paper's ablations (its Table): each one switch of the model, by the name its rows,
# flagfiles (experiments/flags/scenes11_ablation_<name>.flags) and suite runs carry.
ABLATIONS = {
    "no_image_pair": {"use_image_pair": False},
    "no_coordconv": {"use_coordinates": False},
    "no_global_module": {"use_global_module": False},
    "no_flow": {"use_flow": False},
}
# The example-contract keys a model reads for each given pose: the true relative pose
# (a robot's odometry at deployment), or the essential matrix's from the input flow.
POSE_INPUTS = ("rotation", "translation")
GIVEN_POSE_INPUTS = {"pose": POSE_INPUTS, "flow_pose": FLOW_POSE_KEYS}
# The keys a model that reads its pose against the flow reads (refinement, derotation,
# triangulation: the cameras).
CAMERA_INPUTS = ("intrinsics1", "intrinsics2")
# The options that read g as a pose against the flow (they need the cameras, six global
# parameters that stand for a pose, and the flow), with what each does. Those that refine
# the encoder's proposal need the encoder as g's source; the others read any pose g: the
# encoder's, or a given one (odometry, the essential matrix's).
ENCODER_POSE_READERS = {
    "pose_refinement_steps": "refines the encoder's pose on the flow",
    "pose_refinement_starts": "searches around the encoder's pose on the flow",
}
POSE_READERS = {
    "derotate_flow": "subtracts the flow of g's rotation from the flow",
    "parallax_depth": "triangulates the flow under g's pose",
}
# Fixed mixing of a pose into the directions of its given error (`perturbed_pose`; a
# test pins its entries, so that a numpy release that changed the stream is noticed).
_PERTURBATION_MIX = np.random.default_rng(0).normal(0.0, 100.0, (12, 6)).astype(np.float32)


def perturbed_pose(
    rotation: jax.Array,
    translation: jax.Array,
    rotation_degrees: float,
    translation_degrees: float,
) -> tuple[jax.Array, jax.Array]:
    """The relative pose off by exactly the given angles, for studying how accurate a
    pose the model needs (`GlobalLocal.pose_rotation_error`).

    The rotation is composed with a rotation of `rotation_degrees` about an axis, and the
    translation turned by `translation_degrees` about an axis perpendicular to it (its
    norm kept). Both axes are a fixed pseudo-random function of each pair's own pose,
    spread over the directions (the turn's over those perpendicular to t), whatever else
    is in the batch: a pair's given pose is off in the same way at every step and at
    test time; an augmented (rotated or mirrored) copy of it has its own error. Computed
    in float32 at full matmul precision (the directions move by under a degree between
    platforms; the angles are exact on all).

    Args:
      rotation: [B, 3, 3]; translation: [B, 3] (X2 = R X1 + t).
      rotation_degrees, translation_degrees: the errors in degrees, 0 to 180
        (`check_config` refuses others in a model's config).

    Returns:
      (rotation [B, 3, 3], translation [B, 3]) in the inputs' dtype.
    """
    dtype = rotation.dtype
    rotation = rotation.astype(jnp.float32)
    translation = translation.astype(jnp.float32)
    batch_size = rotation.shape[0]
    direction = _unit(translation)
    features = jnp.concatenate([rotation.reshape(batch_size, 9), direction], axis=-1)
    mixed = jnp.matmul(features, _PERTURBATION_MIX, precision=jax.lax.Precision.HIGHEST)
    directions = jnp.sin(mixed)
    rotation_axis = _unit(directions[:, :3])
    turn_axis = _unit(jnp.cross(direction, directions[:, 3:]))
    error = geometry.rotation_matrix(math.radians(rotation_degrees) * rotation_axis)
    turn = geometry.rotation_matrix(math.radians(translation_degrees) * turn_axis)
    rotation = jnp.matmul(error, rotation, precision=jax.lax.Precision.HIGHEST)
    translation = jnp.einsum("bij,bj->bi", turn, translation, precision=jax.lax.Precision.HIGHEST)
    return rotation.astype(dtype), translation.astype(dtype)


def _check_cameras(what: str, intrinsics1, intrinsics2) -> None:
    """Raises ValueError naming `what` needs the cameras when either is missing."""
    if intrinsics1 is None or intrinsics2 is None:
        raise ValueError(
            f"{what}, which needs the cameras: call with intrinsics1= and intrinsics2= [B, 4]"
        )


class GlobalLocal(nn.Module):
    """The paper's global-local network.

    Attributes:
      encoder_channels, encoder_strides: hidden conv layers of the global encoder.
      global_dim: size of the global parameter vector g.
      bank_channels: output channels of the generated 3x3 filter banks.
      kernel_size: spatial size of the generated filters and the final conv.
      use_image_pair: feed the images to the global module (ablation: flow only).
      use_coordinates: append x, y in [-1, 1] to the local input (ablation: no CoordConv).
      use_global_module: generate filters from g (ablation: static learned filters).
      use_flow: use optical flow (ablation: the image pair replaces the flow everywhere).
      local_flow_units: "normalised" gives the local network the same flow as the global
        module (divided by the image size, times `flow_scale`); "pixels" feeds it in
        pixels, as the PyTorch reference does (on gld_scenes/small it learned slower:
        test Abs-Inv 0.0382 vs 0.0336 at step 1000, with flow_scale=1).
      flow_scale: factor on the normalised flow (fractions of the image size) that
        either module sees. Normalised flow has a std of ~0.075 on gld_scenes, against
        ~0.6 for the coordinates and ~0.2 for the images; at 10 the flow is on their
        scale, and the local network learns structure several times faster (within-pair
        correlation 0.76 vs 0.42 after 600 steps with true flow; WORKSPACE.md).
      global_source: "encoder" (the paper's) computes g from the inputs; "pose" gives
        the model the true relative pose instead (the paper's "GT Pose" variant):
        g = `pose_parameters(rotation, translation)`, which the call then needs as
        keyword arguments (the contract's "rotation" and "translation"), and the
        global encoder is not built. Needs global_dim 6. "flow_pose" gives it the pose
        the essential matrix gets from the input flow (`gld.flow_pose`, the contract's
        "flow_rotation" and "flow_translation"): the classical pipeline's motion, no
        label and no odometry needed; a failed estimate gives g = 0.
      pose_rotation_error, pose_translation_error: with global_source="pose", the given
        pose is off by these angles in degrees (`perturbed_pose`): how accurate a pose
        the model needs. 0 (the default) gives the true pose.
      encoder_norm: "instance" standardises each hidden channel of the global encoder
        over the image, per example, before its activation; "none" (the paper's) does
        not (`GlobalEncoder`).
      encoder_coordinates: append x, y in [-1, 1] to the global encoder's input
        (CoordConv for G). The flow of a rotation or a translation depends on where the
        pixel is; a conv encoder that pools globally otherwise sees position only
        through its zero padding. The paper's encoder has none (False).
      pose_refinement_steps: with the encoder as the source of g (global_dim 6), g is
        not the encoder's output but the pose it stands for refined by this many robust
        Gauss-Newton steps on the flow's epipolar geometry (`gld.pose_refinement`;
        the call then needs the cameras' intrinsics1= and intrinsics2=). The encoder
        proposes and geometry refines; no gradient flows through the refinement, so the
        encoder's proposal ("encoder_params") is trained by the epipolar term or the
        pose teacher. 0 (the paper's) uses the encoder's output as g.
      pose_refinement_starts: more than 1 refines not the proposal alone but the best
        of this many translation directions around it, each refined coarsely, then
        anneals the robust scale (`gld.pose_refinement.pose_from_proposal`): a proposal
        in a wrong basin of the translation direction still lands near the motion.
      global_norm: "batch" standardises each global parameter over the batch (running
        statistics at test time), so that g varies across pairs from the first step
        (the pooled encoder output varies by ~0.005 at initialisation); "none" (the
        paper's) leaves it as it is.
      modulation_scale: how far unit-variance global parameters move the generated
        filters at initialisation, as a fraction of the filters' scale.
      filter_formulation: how per-example banks are applied (see `gld.models.filter_banks`);
        None picks the fastest for the platform.
      border: what the local network's convolutions see beyond the image: "zero" (the
        paper's 'SAME' padding) makes the outermost pixels' depth differ from their
        neighbours' (a rim in every depth map); "edge" repeats the input's outermost
        pixels instead (the input padded once by the receptive field's reach, the output
        cropped), so a uniform input gives a uniform depth map to the border.
      derotate_flow: the local network sees the flow less the flow of g's rotation
        (`gld.geometry.rotation_flow`; the call then needs intrinsics1= and
        intrinsics2=): the parallax alone, which lies along the epipolar lines and scales
        with inverse depth. The rotation's flow is quadratic in the pixel's position, which
        filters linear in g cannot subtract. The global module still sees the flow as it
        is. g's pose is the encoder's or a given one (global_source pose, flow_pose).
        False (the paper's) gives the local network the flow.
      parallax_depth: the local network also sees, as two more channels, the inverse depth
        each pixel's flow gives under g's pose and its confidence
        (`parallax_inverse_depth`: a damped linear triangulation; the call then needs
        intrinsics1= and intrinsics2=), which filters linear in g cannot compute from
        the flow (a ratio). False (the paper's) does not.
    """

    encoder_channels: Sequence[int] = option(
        (16, 32, 64, 128, 256), "Global encoder channels.", at_least=1
    )
    encoder_strides: Sequence[int] = option((2, 2, 2, 2, 1), "Global encoder strides.", at_least=1)
    global_dim: int = option(6, "Size of the global parameter vector.", at_least=1)
    bank_channels: Sequence[int] = option(
        (20, 10, 20), "Output channels of the generated banks.", at_least=1
    )
    kernel_size: int = option(3, "Kernel size of generated filters and the final conv.", at_least=1)
    use_image_pair: bool = option(True, "Ablation switch: image pair into the global module.")
    use_coordinates: bool = option(True, "Ablation switch: CoordConv channels.")
    use_global_module: bool = option(True, "Ablation switch: filters generated from g.")
    use_flow: bool = option(True, "Ablation switch: optical flow as the local input.")
    local_flow_units: str = option(
        "normalised", "Units of the local network's flow.", LOCAL_FLOW_UNITS
    )
    flow_scale: float = option(
        layers.FLOW_SCALE, "Factor on the normalised flow fed to both modules.", above=0
    )
    global_source: str = option(
        "encoder",
        "Where g comes from: the global encoder, the true relative pose (odometry), or the "
        "essential matrix's pose from the input flow.",
        GLOBAL_SOURCES,
    )
    pose_rotation_error: float = option(
        0.0,
        "With global_source=pose: the given rotation's error, degrees (0-180; fixed per "
        "pair and augmented copy).",
        at_least=0,
        at_most=180,
    )
    pose_translation_error: float = option(
        0.0,
        "With global_source=pose: the given translation direction's error, degrees (0-180; "
        "fixed per pair and augmented copy).",
        at_least=0,
        at_most=180,
    )
    encoder_norm: str = option("none", "Normalisation inside the global encoder.", ENCODER_NORMS)
    encoder_coordinates: bool = option(False, "CoordConv channels (x, y) into the global encoder.")
    pose_refinement_steps: int = option(
        0,
        "Gauss-Newton steps refining the encoder's pose on the flow's epipolar geometry into "
        "g (0 = the encoder's output is g).",
        at_least=0,
    )
    pose_refinement_starts: int = option(
        1,
        "With more than 1, the refinement first searches this many translation directions "
        "around the encoder's, then anneals its robust scale.",
        at_least=1,
    )
    global_norm: str = option("none", "Normalisation of g.", GLOBAL_NORMS)
    modulation_scale: float = option(
        MODULATION_SCALE, "Initial modulation of the filters by g.", at_least=0
    )
    filter_formulation: str | None = option(
        None, "apply_filter_banks formulation (default: the platform's).", tuple(FORMULATIONS)
    )
    border: str = option("zero", "The local network's padding beyond the image.", BORDERS)
    derotate_flow: bool = option(
        False, "The local network sees the flow less the flow of g's rotation (the parallax)."
    )
    parallax_depth: bool = option(
        False, "The local network also sees the inverse depth the flow gives under g's pose."
    )

    @property
    def local_in_channels(self) -> int:
        """Channels of the local network's input."""
        flow_channels = 2 + (2 if self.parallax_depth else 0)
        return (flow_channels if self.use_flow else 6) + (2 if self.use_coordinates else 0)

    @property
    def extra_inputs(self) -> tuple[str, ...]:
        """Contract keys the call reads by keyword besides the images and flow."""
        if not self.use_global_module:
            return ()
        reads_pose = self.pose_refinement_steps or any(getattr(self, name) for name in POSE_READERS)
        given = GIVEN_POSE_INPUTS.get(self.global_source, ())
        return tuple(given) + (CAMERA_INPUTS if reads_pose else ())

    @nn.compact
    def __call__(
        self,
        image1: jax.Array,
        image2: jax.Array,
        flow: jax.Array,
        *,
        rotation: jax.Array | None = None,
        translation: jax.Array | None = None,
        flow_rotation: jax.Array | None = None,
        flow_translation: jax.Array | None = None,
        intrinsics1: jax.Array | None = None,
        intrinsics2: jax.Array | None = None,
        train: bool = False,
    ) -> dict[str, jax.Array]:
        """Predicts inverse depth for view 1.

        Args:
          image1, image2: [B, H, W, 3] float32 in [-0.5, 0.5].
          flow: [B, H, W, 2] pixels, I1 -> I2.
          rotation, translation: [B, 3, 3] and [B, 3], the relative pose; read only
            with global_source="pose".
          flow_rotation, flow_translation: the same, estimated from the input flow;
            read only with global_source="flow_pose".
          intrinsics1, intrinsics2: [B, 4] normalised; read only with
            pose_refinement_steps, derotate_flow or parallax_depth.
          train: batch statistics (global_norm="batch") come from the batch and are
            recorded when True, from the running averages when False.

        Returns:
          {"inv_depth": [B, H, W] positive, "depth": [B, H, W],
           "global_params": [B, global_dim] (zeros without a global module),
           "global_pose": the pose g stands for (`global_params_pose`; with a global
             module and global_dim 6),
           "filter_banks": list of FilterBank(kernel [B, k, k, C_in, C_out], bias [B, C_out])}.
        """
        layers.check_inputs(image1, image2, flow)
        batch_size, height, width, _ = flow.shape
        image_pair = jnp.concatenate([image1, image2], axis=-1)
        normalised_flow = layers.scaled_flow(flow, self.flow_scale)

        if self.local_flow_units not in LOCAL_FLOW_UNITS:
            raise ValueError(
                f"local_flow_units must be one of {LOCAL_FLOW_UNITS}, got {self.local_flow_units!r}"
            )
        if self.use_flow:
            local_inputs = flow if self.local_flow_units == "pixels" else normalised_flow
            global_inputs = layers.global_module_inputs(
                image1, image2, normalised_flow, self.use_image_pair
            )
        else:
            local_inputs = image_pair
            global_inputs = image_pair
        if self.encoder_coordinates:
            global_inputs = layers.with_coordinates(global_inputs)

        bank_kwargs = dict(
            in_channels=self.local_in_channels,
            bank_channels=tuple(self.bank_channels),
            kernel_size=self.kernel_size,
        )
        if self.global_source not in GLOBAL_SOURCES:
            raise ValueError(
                f"global_source must be one of {GLOBAL_SOURCES}, got {self.global_source!r}"
            )
        if self.use_global_module and self.global_source in GIVEN_POSE_INPUTS:
            rotation_key, translation_key = GIVEN_POSE_INPUTS[self.global_source]
            if self.global_source == "flow_pose":
                rotation, translation = flow_rotation, flow_translation
            if rotation is None or translation is None:
                raise ValueError(
                    f'global_source="{self.global_source}" needs the relative pose: call with '
                    f"{rotation_key}= [B, 3, 3] and {translation_key}= [B, 3]"
                )
            if self.global_dim != 6:
                raise ValueError(
                    f'global_source="{self.global_source}" gives 6 global parameters; '
                    f"global_dim is {self.global_dim}"
                )
            if rotation.shape[0] != batch_size or translation.shape[0] != batch_size:
                raise ValueError(
                    f"rotation {rotation.shape} and translation {translation.shape} must "
                    f"have the batch size of the flow ({batch_size})"
                )
            if self.pose_rotation_error or self.pose_translation_error:
                rotation, translation = perturbed_pose(
                    rotation, translation, self.pose_rotation_error, self.pose_translation_error
                )
            global_params = pose_parameters(rotation, translation).astype(flow.dtype)
        elif self.use_global_module:
            global_params = GlobalEncoder(
                channels=tuple(self.encoder_channels),
                strides=tuple(self.encoder_strides),
                global_dim=self.global_dim,
                kernel_size=self.kernel_size,
                norm=self.encoder_norm,
                name="global_encoder",
            )(global_inputs)
            encoder_params = global_params
            if self.pose_refinement_steps:
                global_params = self._refined(global_params, flow, intrinsics1, intrinsics2)
        if self.global_norm not in GLOBAL_NORMS:
            raise ValueError(f"global_norm must be one of {GLOBAL_NORMS}, got {self.global_norm!r}")
        # The pose g stands for, before any normalisation: what derotation and
        # triangulation read.
        pose_params = global_params if self.use_global_module else None
        if self.use_global_module:
            if self.global_norm == "batch":
                global_params = nn.BatchNorm(
                    use_running_average=not train,
                    use_bias=False,
                    use_scale=False,
                    momentum=0.99,
                    # g's variance starts near 1e-5: a larger epsilon would shrink it.
                    epsilon=1e-8,
                    name="global_norm",
                )(global_params)
            filter_banks = HyperNetwork(
                **bank_kwargs, modulation_scale=self.modulation_scale, name="hypernet"
            )(global_params)
        else:
            global_params = pose_params = jnp.zeros((batch_size, self.global_dim), flow.dtype)
            filter_banks = StaticFilterBanks(**bank_kwargs, name="static_filters")(batch_size)
        if self.derotate_flow:
            local_inputs = self._derotated(flow, pose_params, intrinsics1, intrinsics2)
        if self.parallax_depth:
            _check_cameras("parallax_depth triangulates under g's pose", intrinsics1, intrinsics2)
            depth_channel = parallax_inverse_depth(flow, pose_params, intrinsics1, intrinsics2)
            local_inputs = jnp.concatenate([local_inputs, depth_channel], axis=-1)
        if self.use_coordinates:
            local_inputs = layers.with_coordinates(local_inputs)

        final_conv = ConvParameters(
            in_channels=self.bank_channels[-1],
            out_channels=1,
            kernel_size=self.kernel_size,
            name="final_conv",
        )()
        if self.border not in BORDERS:
            raise ValueError(f"border must be one of {BORDERS}, got {self.border!r}")
        # The banks and the head each reach kernel_size // 2 pixels further out.
        reach = (len(self.bank_channels) + 1) * (self.kernel_size // 2)
        if self.border == "edge" and reach:
            widths = ((0, 0), (reach, reach), (reach, reach), (0, 0))
            local_inputs = jnp.pad(local_inputs, widths, mode="edge")
        logits = apply_filter_banks(
            filter_banks, local_inputs, head=final_conv, formulation=self.filter_formulation
        )
        if self.border == "edge" and reach:
            logits = logits[:, reach:-reach, reach:-reach]
        outputs = layers.depth_outputs(logits)
        outputs["global_params"] = global_params
        if self.use_global_module and self.global_dim == 6:
            outputs["global_pose"] = global_params_pose(global_params)
        if (
            self.use_global_module
            and self.global_source == "encoder"
            and self.pose_refinement_steps
        ):
            outputs["encoder_params"] = encoder_params
            outputs["encoder_pose"] = global_params_pose(encoder_params)
        outputs["filter_banks"] = list(filter_banks)
        return outputs

    def _derotated(self, flow, global_params, intrinsics1, intrinsics2):
        """The local network's flow less the flow of g's rotation, in its units."""
        _check_cameras("derotate_flow subtracts the flow of g's rotation", intrinsics1, intrinsics2)
        parallax = parallax_flow(flow, global_params, intrinsics1, intrinsics2)
        if self.local_flow_units == "pixels":
            return parallax
        return layers.scaled_flow(parallax, self.flow_scale)

    def _refined(self, proposal, flow, intrinsics1, intrinsics2):
        """The global parameters of the encoder's pose refined on the flow."""
        _check_cameras(
            "pose_refinement_steps refines the pose on the flow's epipolar geometry",
            intrinsics1,
            intrinsics2,
        )
        if self.global_dim != 6:
            raise ValueError(
                f"pose_refinement_steps needs 6 global parameters (a pose); global_dim is "
                f"{self.global_dim}"
            )
        pose = global_params_pose(jax.lax.stop_gradient(proposal))
        rotation, translation = pose_refinement.pose_from_proposal(
            jax.lax.stop_gradient(flow),
            pose["rotation"],
            pose["translation"],
            intrinsics1,
            intrinsics2,
            iterations=self.pose_refinement_steps,
            starts=self.pose_refinement_starts,
        )
        return jax.lax.stop_gradient(pose_parameters(rotation, translation)).astype(flow.dtype)


class ConvParameters(nn.Module):
    """The kernel and bias of a conv shared by the batch, initialised like `nn.Conv`.

    The local network's final conv is applied by `apply_filter_banks` (as its head,
    next to the per-example banks), so the model holds only its parameters; names and
    initialisation are those of `nn.Conv`.
    """

    in_channels: int
    out_channels: int
    kernel_size: int = 3

    @nn.compact
    def __call__(self) -> SharedConv:
        """Returns SharedConv(kernel [k, k, C_in, C_out], bias [C_out])."""
        shape = (self.kernel_size, self.kernel_size, self.in_channels, self.out_channels)
        kernel = self.param("kernel", nn.initializers.lecun_normal(), shape)
        bias = self.param("bias", nn.initializers.zeros_init(), (self.out_channels,))
        return SharedConv(kernel=kernel, bias=bias)
