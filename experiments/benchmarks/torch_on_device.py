"""The PyTorch reference on an accelerator, timed with the device synchronised.

    python3 experiments/benchmarks/torch_on_device.py --device=cuda [--repeats=20]
    python -m experiments.benchmark --torch_python=python3 --torch_device=cuda

`../shared/bench/torch_reference.py` defines the peer network, its batches and its loss,
and times them on the CPU. On a GPU its timer would measure kernel launches, not
kernels: PyTorch returns before the device has finished. This runner imports that
file's network, batch and loss unchanged, moves them to `--device`, and times each
call between two device synchronisations (after one warm-up call, median of
`--repeats`). It prints the reference's JSON (milliseconds), with the device's name.
It runs under a Python with torch; gld never imports it.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import time
from pathlib import Path

import torch

DEFAULT_REFERENCE = Path(__file__).resolve().parents[3] / "shared" / "bench" / "torch_reference.py"


def load_reference(path: Path):
    spec = importlib.util.spec_from_file_location("torch_reference", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def median_ms(fn, repeats: int, device: torch.device) -> float:
    """Median milliseconds of `fn` between device synchronisations, after one warm-up."""

    def synchronise() -> None:
        if device.type == "cuda":
            torch.cuda.synchronize(device)

    fn()
    synchronise()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        synchronise()
        times.append((time.perf_counter() - start) * 1000)
    return round(statistics.median(times), 3)


def measure(reference, model, forward, repeats: int, device: torch.device) -> dict:
    def on_device(batch):
        return {key: value.to(device) for key, value in batch.items()}

    out = {}
    with torch.no_grad():
        for size in (1, 16):
            data = on_device(reference.batch(size))
            out[f"forward_b{size}_ms"] = median_ms(
                lambda data=data: forward(data["image1"], data["image2"], data["flow"]),
                repeats,
                device,
            )
    data = on_device(reference.batch(16))
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)

    def step():
        optimizer.zero_grad(set_to_none=True)
        prediction = forward(data["image1"], data["image2"], data["flow"])
        reference.loss_fn(prediction, data, data["image1"]).backward()
        optimizer.step()

    out["train_b16_ms"] = median_ms(step, repeats, device)
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE)
    parser.add_argument("--no-compile", action="store_true")
    args = parser.parse_args()
    if not args.reference.is_file():
        parser.error(f"the PyTorch reference is not at {args.reference}")
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        parser.error("--device=cuda, but torch sees no CUDA device")
    reference = load_reference(args.reference)
    torch.manual_seed(0)
    model = reference.GlobalLocal().to(device)
    result = {
        "torch": torch.__version__,
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu",
        "tf32_matmul": torch.backends.cuda.matmul.allow_tf32,
        "tf32_conv": torch.backends.cudnn.allow_tf32,
        "params": sum(p.numel() for p in model.parameters()),
        "eager": measure(reference, model, model, args.repeats, device),
    }
    if not args.no_compile:
        compiled = torch.compile(model)
        result["compiled"] = measure(reference, model, compiled, args.repeats, device)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
