"""The global-local model written out in plain numpy, from the paper and the docstrings:
the reference that the Flax model, its exports and the predictor are checked against.

Global encoder: 3x3 'SAME' convolutions (flax's padding: the extra pixel of an odd pad
at the end), LeakyReLU 0.2 after each hidden one, a conv to the global parameters, the
spatial mean. Hypernetwork: one linear layer, g @ W + b, read as (kernel [k, k, C_in,
C_out], bias [C_out]) per bank, in order. Local network: per example, each bank then a
LeakyReLU, then the shared final conv, on [flow / [W, H] * flow_scale, x, y] with x, y
evenly spaced in [-1, 1]. Inverse depth: softplus of the logit, offset so that 0 gives
`INITIAL_INV_DEPTH`, plus `MIN_INV_DEPTH`.
"""

import math

import numpy as np

from gld.models.layers import INITIAL_INV_DEPTH, MIN_INV_DEPTH

NEGATIVE_SLOPE = 0.2  # the paper's LeakyReLU


def leaky_relu(x):
    return np.where(x > 0, x, NEGATIVE_SLOPE * x)


def conv_same(inputs, kernel, bias, stride=1):
    """inputs [B, H, W, C_in], kernel [k, k, C_in, C_out], bias [C_out] -> 'SAME' conv
    [B, ceil(H / stride), ceil(W / stride), C_out], float64, as a sum over kernel taps."""
    inputs, kernel = np.asarray(inputs, np.float64), np.asarray(kernel, np.float64)
    _, height, width, _ = inputs.shape
    size = kernel.shape[0]
    out_height, out_width = -(-height // stride), -(-width // stride)
    pad_rows = max((out_height - 1) * stride + size - height, 0)
    pad_cols = max((out_width - 1) * stride + size - width, 0)
    padded = np.pad(
        inputs,
        (
            (0, 0),
            (pad_rows // 2, pad_rows - pad_rows // 2),
            (pad_cols // 2, pad_cols - pad_cols // 2),
            (0, 0),
        ),
    )
    out = np.zeros((inputs.shape[0], out_height, out_width, kernel.shape[-1]))
    for row in range(size):
        for col in range(size):
            taps = padded[
                :,
                row : row + stride * (out_height - 1) + 1 : stride,
                col : col + stride * (out_width - 1) + 1 : stride,
            ]
            out += taps @ kernel[row, col]
    return out + np.asarray(bias, np.float64)


def encoder(params, inputs, strides):
    """The global encoder: params {"conv0": {"kernel", "bias"}, ..., "to_global"}."""
    features = inputs
    for index, stride in enumerate(strides):
        layer = params[f"conv{index}"]
        features = leaky_relu(conv_same(features, layer["kernel"], layer["bias"], stride))
    final = conv_same(features, params["to_global"]["kernel"], params["to_global"]["bias"])
    return final.mean(axis=(1, 2))


def hypernet(params, global_params, in_channels, bank_channels, kernel_size):
    """[(kernel [B, k, k, C_in, C_out], bias [B, C_out]), ...]: g @ W + b, split in order."""
    weights, offset = params["linear"], 0
    flat = np.asarray(global_params, np.float64) @ np.asarray(weights["kernel"], np.float64)
    flat = flat + np.asarray(weights["bias"], np.float64)
    banks, channels = [], [in_channels, *bank_channels]
    for c_in, c_out in zip(channels[:-1], channels[1:], strict=True):
        entries = kernel_size * kernel_size * c_in
        kernel = flat[:, offset : offset + entries * c_out]
        offset += entries * c_out
        bias = flat[:, offset : offset + c_out]
        offset += c_out
        banks.append((kernel.reshape(-1, kernel_size, kernel_size, c_in, c_out), bias))
    assert offset == flat.shape[1], (offset, flat.shape)
    return banks


def local_network(banks, final_conv, local_inputs):
    """Each example through its own banks (a Python loop), then the shared final conv:
    logits [B, H, W]."""
    logits = []
    for index in range(local_inputs.shape[0]):
        features = local_inputs[index : index + 1]
        for kernel, bias in banks:
            features = leaky_relu(conv_same(features, kernel[index], bias[index]))
        logits.append(conv_same(features, final_conv["kernel"], final_conv["bias"])[0, ..., 0])
    return np.stack(logits)


def inv_depth_of(logits):
    offset = math.log(math.expm1(INITIAL_INV_DEPTH))
    return np.logaddexp(0.0, logits + offset) + MIN_INV_DEPTH


def coordinates(height, width):
    """[H, W, 2]: x then y, each evenly spaced from -1 to 1."""
    y, x = np.meshgrid(np.linspace(-1, 1, height), np.linspace(-1, 1, width), indexing="ij")
    return np.stack([x, y], axis=-1)


def global_local(model, variables, image1, image2, flow, global_params=None):
    """The model's outputs, in numpy: {"inv_depth", "depth", "global_params", "banks"}.

    `model` supplies the architecture (a `GlobalLocal` with its global module, normalised
    local flow and coordinates); `global_params` [B, G], when given, replaces the
    encoder's (a model given the pose).
    """
    params = variables["params"]
    batch_size, height, width, _ = np.shape(flow)
    scaled_flow = np.asarray(flow, np.float64) / [width, height] * model.flow_scale
    if global_params is None:
        global_inputs = np.concatenate([image1, image2, scaled_flow], axis=-1)
        global_params = encoder(params["global_encoder"], global_inputs, model.encoder_strides)
    banks = hypernet(
        params["hypernet"],
        global_params,
        model.local_in_channels,
        model.bank_channels,
        model.kernel_size,
    )
    grid = np.broadcast_to(coordinates(height, width), (batch_size, height, width, 2))
    local_inputs = np.concatenate([scaled_flow, grid], axis=-1)
    inv_depth = inv_depth_of(local_network(banks, params["final_conv"], local_inputs))
    return {
        "inv_depth": inv_depth,
        "depth": 1.0 / inv_depth,
        "global_params": np.asarray(global_params, np.float64),
        "banks": banks,
    }
