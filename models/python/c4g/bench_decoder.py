"""The exact decoder's speed, ONNX Runtime against PyTorch eager, measured in one run.

    python -m c4g.bench_decoder --config official --frames 4 16 --batch 1 4 [--profile DIR]

Builds the model at `--config` with random weights (the cost does not depend on the values),
exports the decoder graph as the export tool does (fused attention, the last layer's query rows
only), and times one decoder call per (T, B) both ways, alternating ONNX Runtime and PyTorch so
that a noisy machine slows both alike: the median of `--repeats` calls each, and their ratio.
ONNX Runtime runs with the engine's session settings (CPU provider, no arena, one thread per core),
PyTorch with as many threads. `--settings` times ONNX Runtime's session settings against each
other instead (arena, thread spinning). `--profile` also writes ONNX Runtime's per-node profile of one call
and prints the time per operator type, which is where the exact speed-ups are found.

The features are random, and the times are the reference normalisation of context frames 0..T-1
for a target in the middle of the span.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from .attention import fused_export
from .export import DecoderGraph, _config, _export_graph, build_model


def session_options(profile_dir: Path | None = None, arena: bool = False, spinning: bool = True) -> ort.SessionOptions:
    """The engine's session settings: c4g-runtime's defaults (CPU arena off, threads spinning,
    default thread count), or the `C4G_CPU_ARENA` / `C4G_INTRA_OP_SPINNING` ones asked for."""
    options = ort.SessionOptions()
    options.enable_cpu_mem_arena = arena
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    if profile_dir is not None:
        options.enable_profiling = True
        options.profile_file_prefix = str(profile_dir / "decoder")
    return options


def inputs(cfg, frames: int, batch: int, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    features = rng.standard_normal((frames, cfg.tokens_per_frame, cfg.feature_width)).astype(np.float32)
    context = np.arange(frames, dtype=np.float64)
    targets = np.linspace(0.25, 0.75, batch) * max(frames - 1, 1) + 0.5 * (frames == 1)
    m = context.min()
    rows = [((context - m) / (t - m + 1e-8)).astype(np.float32) for t in targets]
    target_times = np.array([(t - m) / (t - m + 1e-8) for t in targets], np.float32)
    return {"features": features, "context_times": np.stack(rows), "target_times": target_times}


def per_op(profile: Path) -> dict[str, float]:
    """Milliseconds per operator type in an ONNX Runtime profile (node kernel times)."""
    events = json.loads(profile.read_text())
    totals: dict[str, float] = defaultdict(float)
    for e in events:
        if e.get("cat") == "Node" and e.get("name", "").endswith("_kernel_time"):
            totals[e.get("args", {}).get("op_name", "?")] += e["dur"] / 1000.0
    return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


SETTINGS = {
    "engine default (no arena, spinning)": (False, True),
    "C4G_CPU_ARENA=true": (True, True),
    "C4G_INTRA_OP_SPINNING=false": (False, False),
    "both": (True, False),
}


def compare_settings(path: Path, cfg, args) -> None:
    """One session per setting, timed call by call in turn (median of `--repeats` each)."""
    sessions = {
        name: ort.InferenceSession(str(path), session_options(None, arena, spinning), providers=["CPUExecutionProvider"])
        for name, (arena, spinning) in SETTINGS.items()
    }
    for frames in args.frames:
        for batch in args.batch:
            feeds = inputs(cfg, frames, batch)
            for s in sessions.values():
                s.run(None, feeds)
            times: dict[str, list[float]] = {name: [] for name in sessions}
            for _ in range(args.repeats):
                for name, s in sessions.items():
                    t = time.perf_counter()
                    s.run(None, feeds)
                    times[name].append(time.perf_counter() - t)
            print(f"T={frames} B={batch}: " + ", ".join(f"{k} {statistics.median(v):.2f} s" for k, v in times.items()), flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench_decoder", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="official")
    ap.add_argument("--frames", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--batch", type=int, nargs="+", default=[1])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--arena", action="store_true", help="ONNX Runtime's CPU arena on (C4G_CPU_ARENA=true)")
    ap.add_argument("--no-spinning", action="store_true", help="intra-op threads do not spin (C4G_INTRA_OP_SPINNING=false)")
    ap.add_argument(
        "--settings",
        action="store_true",
        help="instead of PyTorch, compare ONNX Runtime's session settings: the engine default, arena on, spinning off, both",
    )
    ap.add_argument("--profile", type=Path, help="write an ONNX Runtime profile of one call per setting here")
    ap.add_argument("--json", type=Path, help="also write the results as JSON")
    args = ap.parse_args(argv)
    threads = os.cpu_count() or 1
    torch.set_num_threads(threads)
    cfg = _config(args.config, 0)
    t0 = time.perf_counter()
    model = build_model(cfg, seed=0, checkpoint=None)
    print(f"model: {args.config}, {sum(p.numel() for p in model.parameters()):,} parameters ({time.perf_counter() - t0:.0f} s to build)", flush=True)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "decoder.onnx"
        f = torch.zeros(2, cfg.tokens_per_frame, cfg.feature_width)
        with torch.no_grad(), fused_export(True):
            _export_graph(
                DecoderGraph(model), (f, torch.zeros(2, 2), torch.zeros(2)), path,
                {"features": {0: "T"}, "context_times": {0: "B", 1: "T"}, "target_times": {0: "B"}}, {"gaussians": {0: "B"}},
            )  # fmt: skip
        if args.settings:
            del model
            compare_settings(path, cfg, args)
            return 0
        sess = ort.InferenceSession(str(path), session_options(None, args.arena, not args.no_spinning), providers=["CPUExecutionProvider"])
        for frames in args.frames:
            for batch in args.batch:
                feeds = inputs(cfg, frames, batch)
                tensors = {k: torch.from_numpy(v) for k, v in feeds.items()}
                with torch.inference_mode():
                    sess.run(None, feeds)  # warm-up (first-run allocations, prepacking)
                    model.decode_canonical(*tensors.values())
                    ort_times, torch_times = [], []
                    for _ in range(args.repeats):
                        t = time.perf_counter()
                        (ours,) = sess.run(None, feeds)
                        ort_times.append(time.perf_counter() - t)
                        t = time.perf_counter()
                        theirs = model.decode_canonical(*tensors.values()).numpy()
                        torch_times.append(time.perf_counter() - t)
                diff = float(np.abs(ours - theirs).max())
                row = {
                    "frames": frames, "batch": batch, "onnxruntime_s": statistics.median(ort_times),
                    "pytorch_s": statistics.median(torch_times), "max_abs_diff": diff,
                }  # fmt: skip
                row["ratio"] = row["onnxruntime_s"] / row["pytorch_s"]
                results.append(row)
                print(
                    f"T={frames:3d} B={batch}: onnxruntime {row['onnxruntime_s']:.3f} s ({row['onnxruntime_s'] / batch:.3f} s a target), "
                    f"pytorch {row['pytorch_s']:.3f} s, ratio {row['ratio']:.2f}, outputs differ by {diff:.1e}",
                    flush=True,
                )
                if args.profile:
                    args.profile.mkdir(parents=True, exist_ok=True)
                    prof = ort.InferenceSession(str(path), session_options(args.profile, args.arena, not args.no_spinning), providers=["CPUExecutionProvider"])
                    prof.run(None, feeds)
                    prof.run(None, feeds)
                    ops = per_op(Path(prof.end_profiling()))
                    total = sum(ops.values())
                    print("  per operator (ms, 2 calls): " + ", ".join(f"{k} {v:.0f} ({v / total:.0%})" for k, v in list(ops.items())[:8]))
    if args.json:
        args.json.write_text(json.dumps({"config": args.config, "threads": threads, "results": results}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
