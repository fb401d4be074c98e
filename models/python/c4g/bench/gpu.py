"""The model's cost on a GPU through the PyTorch mirror: the bar the ONNX path must reach there.

    python -m c4g.bench.gpu --config official [--frames 4 16] [--batch 1 16] [--dtype bf16 fp16]

Builds the model at `--config` with random weights (the cost does not depend on the values), on
`--device` (default `cuda`), in each `--dtype` (a copy of the f32 weights each), and times the encoder on T context frames and the
decoder on B targets of a T-frame encoding (T from `--frames`, B from `--batch`): the median of
`--repeats` calls after a warm-up, each call timed with CUDA events (wall clock on the CPU). The
floating-point operations of one call are counted by `torch.utils.flop_counter` (matrix products
and attention, which are nearly all of the work), so each row says what fraction of the device's
peak it reaches: the peak of a large matrix product of the same dtype measured in the same run,
and the vendor's dense figure where the device is known (`PEAKS`).

Prints a Markdown table (and `--json FILE` writes the rows) for `docs/benchmarks.md`;
`scripts/device-check` runs it. On a machine without CUDA, `--device cpu --config official-small`
checks that it runs.
"""

from __future__ import annotations

import argparse
import copy
import json
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from c4g.package.export import _config, build_model

# Dense (no sparsity) peak TFLOP/s by device name and dtype, from the vendors' data sheets.
PEAKS = {
    "H200": {"bf16": 989.0, "fp16": 989.0, "fp32": 67.0},
    "H100": {"bf16": 989.0, "fp16": 989.0, "fp32": 67.0},
    "A100": {"bf16": 312.0, "fp16": 312.0, "fp32": 19.5},
}

DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16, "fp32": torch.float32}


def timed(fn, device: torch.device, repeats: int) -> float:
    """Median seconds of `repeats` calls of `fn`, after two warm-up calls."""
    for _ in range(2):
        fn()
    samples = []
    for _ in range(repeats):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            torch.cuda.synchronize()
            samples.append(start.elapsed_time(end) / 1e3)
        else:
            t = time.perf_counter()
            fn()
            samples.append(time.perf_counter() - t)
    return statistics.median(samples)


def flops(fn) -> int:
    """Floating-point operations of one call of `fn` (matrix products and attention)."""
    counter = FlopCounterMode(display=False)
    with counter:
        fn()
    return counter.get_total_flops()


def matmul_peak(device: torch.device, dtype: torch.dtype, repeats: int) -> float:
    """TFLOP/s of a large square matrix product: what this device reaches in practice."""
    n = 8192 if device.type == "cuda" else 1024
    a = torch.randn(n, n, device=device, dtype=dtype)
    b = torch.randn(n, n, device=device, dtype=dtype)
    seconds = timed(lambda: a @ b, device, repeats)
    return 2 * n**3 / seconds / 1e12


def vendor_peak(device: torch.device, dtype_name: str) -> float | None:
    if device.type != "cuda":
        return None
    name = torch.cuda.get_device_name(device)
    for key, peaks in PEAKS.items():
        if key in name:
            return peaks.get(dtype_name)
    return None


def bench(model, cfg, device: torch.device, dtype_name: str, args) -> dict:
    """One dtype's table (printed) and its rows."""
    dtype = DTYPES[dtype_name]
    measured_peak = matmul_peak(device, dtype, args.repeats)
    spec_peak = vendor_peak(device, dtype_name)
    print()
    print(f"{dtype_name}:")
    n = 8192 if device.type == "cuda" else 1024
    print(f"peak: {measured_peak:.3g} TFLOP/s measured ({n}² matrix product)" + (f", {spec_peak:.0f} data sheet" if spec_peak else ""))
    print()
    print("| call | T | B | ms | TFLOP | TFLOP/s | of measured peak | of data-sheet peak |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    size = cfg.image_size
    with torch.no_grad():
        for frames in args.frames:
            images = torch.rand(frames, 3, size, size, device=device, dtype=dtype) * 2 - 1
            calls = [("encode", 0, lambda images=images: model.encode(images))]
            features = model.encode(images)
            context = torch.linspace(0, 1, frames, device=device, dtype=dtype)
            for batch in args.batch:
                ctx = context[None].expand(batch, -1).contiguous()
                tgt = torch.linspace(0.25, 0.75, batch, device=device, dtype=dtype)
                calls.append(("decode", batch, lambda f=features, c=ctx, t=tgt: model.decode_raw(f, c, t)))
            for call, batch, fn in calls:
                work = flops(fn)
                seconds = timed(fn, device, args.repeats)
                rate = work / seconds / 1e12
                row = {
                    "call": call,
                    "frames": frames,
                    "batch": batch,
                    "ms": seconds * 1e3,
                    "tflop": work / 1e12,
                    "tflops": rate,
                    "of_measured_peak": rate / measured_peak,
                    "of_spec_peak": rate / spec_peak if spec_peak else None,
                }
                rows.append(row)
                spec = f"{row['of_spec_peak']:.1%}" if spec_peak else "n/a"
                print(
                    f"| {call} | {frames} | {batch or '-'} | {row['ms']:.2f} | {row['tflop']:.4g} | {rate:.3g} "
                    f"| {row['of_measured_peak']:.1%} | {spec} |",
                    flush=True,
                )
    return {"dtype": dtype_name, "measured_peak_tflops": measured_peak, "spec_peak_tflops": spec_peak, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.gpu", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="official", help="a preset (official, official-small) or a config JSON")
    ap.add_argument("--frames", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--batch", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--dtype", choices=sorted(DTYPES), nargs="+", default=["bf16"])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--repeats", type=int, default=10)
    ap.add_argument("--json", type=Path, help="also write the rows here")
    args = ap.parse_args(argv)

    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("c4g.bench.gpu: CUDA is not available (use --device cpu to check the harness)", file=sys.stderr)
        return 2
    cfg = _config(args.config, 0)
    base = build_model(cfg, seed=0, checkpoint=None)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU"
    print(f"device: {name}; torch {torch.__version__}; config {args.config}")
    runs = []
    for dtype_name in args.dtype:
        model = copy.deepcopy(base).to(device=device, dtype=DTYPES[dtype_name])
        runs.append(bench(model, cfg, device, dtype_name, args))
        del model
        if device.type == "cuda":
            torch.cuda.empty_cache()
    if args.json:
        args.json.write_text(json.dumps({"device": name, "runs": runs}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
