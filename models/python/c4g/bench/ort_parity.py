"""A package's graphs on ONNX Runtime's CUDA provider against its CPU provider: parity and time.

    python -m c4g.bench.ort_parity models/fixtures/c4g-small [--frames 4] [--batch 2]

Runs the encoder on T random frames and the decoder on its features for B targets, once on each
provider (CPU first: the reference), and prints the largest difference of each output and each
provider's median time of 5 calls. Exits 2, saying so, where this ONNX Runtime has no CUDA
provider (the `onnxruntime` wheel is CPU-only; `onnxruntime-gpu` has it): `scripts/device-check`
reports that as "not run".

Tolerance: the CUDA kernels sum in other orders (and may use TF32 for float32 products), so the
outputs differ by rounding; 1e-2 absolute on the Gaussians' raw parameters flags a real fault
(a wrong kernel or layout gives differences of order one), not TF32's 1e-3-relative rounding.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort

TOLERANCE = 1e-2


def median_seconds(fn, repeats: int = 5) -> float:
    fn()
    samples = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - t)
    return statistics.median(samples)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.ort_parity", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("package", type=Path)
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--batch", type=int, default=2)
    args = ap.parse_args(argv)

    if "CUDAExecutionProvider" not in ort.get_available_providers():
        print(f"ort_parity: this ONNX Runtime ({ort.__version__}) has no CUDA provider: {ort.get_available_providers()}")
        return 2
    manifest = json.loads((args.package / "model.json").read_text())
    size = manifest["input"]["height"], manifest["input"]["width"]
    rng = np.random.default_rng(0)
    frames = rng.uniform(-1, 1, (args.frames, 3, *size)).astype(np.float32)
    context = np.tile(np.linspace(0, 1, args.frames, dtype=np.float32), (args.batch, 1))
    targets = np.linspace(0.2, 0.8, args.batch, dtype=np.float32)

    results = {}
    for provider in ["CPUExecutionProvider", "CUDAExecutionProvider"]:
        encoder = ort.InferenceSession(str(args.package / "encoder.onnx"), providers=[provider])
        decoder = ort.InferenceSession(str(args.package / "decoder.onnx"), providers=[provider])
        if provider not in encoder.get_providers():
            print(f"ort_parity: {provider} did not load: {encoder.get_providers()}")
            return 2
        (features,) = encoder.run(None, {"frames": frames})
        feeds = {"features": features, "context_times": context, "target_times": targets}
        (gaussians,) = decoder.run(None, feeds)
        results[provider] = {
            "features": features,
            "gaussians": gaussians,
            "encode_s": median_seconds(lambda: encoder.run(None, {"frames": frames})),
            "decode_s": median_seconds(lambda: decoder.run(None, feeds)),
        }
    cpu, cuda = results["CPUExecutionProvider"], results["CUDAExecutionProvider"]
    worst = 0.0
    for name in ["features", "gaussians"]:
        diff = float(np.abs(cpu[name] - cuda[name]).max())
        worst = max(worst, diff)
        print(f"{name}: largest |CUDA - CPU| {diff:.2e}")
    print(
        f"encode T={args.frames}: CPU {cpu['encode_s'] * 1e3:.1f} ms, CUDA {cuda['encode_s'] * 1e3:.1f} ms; "
        f"decode B={args.batch}: CPU {cpu['decode_s'] * 1e3:.1f} ms, CUDA {cuda['decode_s'] * 1e3:.1f} ms"
    )
    ok = worst <= TOLERANCE
    print(f"parity: {'ok' if ok else 'FAILED'} (tolerance {TOLERANCE})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
