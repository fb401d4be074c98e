"""The exact decoder's speed, ONNX Runtime against PyTorch eager, measured in one run.

    python -m c4g.bench.decoder --config official --frames 4 16 --batch 1 4 [--profile DIR]

Builds the model at `--config` with random weights (the cost does not depend on the values),
exports the decoder graphs as the export tool does (fused attention, the last layer's query rows
only) in both decoder forms, and times one decoder call per (T, B) every way, call by call in turn
so that a noisy machine slows all alike: the median of `--repeats` calls each, and each one's ratio
to PyTorch eager (our mirror, the plain form: `C4G.decode_canonical`). The ways: ONNX Runtime on the
plain decoder and on the precomputed one (`c4g.model.precomputed`; its context projection runs once per
clip, before the timed calls, and is timed on its own), both with ONNX Runtime's session defaults
(CPU provider, no arena, threads spinning, one thread per core: the engine's until the measurements
here made arena on and spinning off its default), and the precomputed one again with
`C4G_CPU_ARENA=true` and `C4G_INTRA_OP_SPINNING=false`, also as it was exported before the last
layer's qkv projection was split (`precomputed-unsplit`: one product, q for every row; see
`decoder.DecoderAttention.split_projection`); PyTorch with as many threads. `--forms` picks the
graphs. `--settings` times ONNX Runtime's session settings against each other instead (arena,
thread spinning, denormals as zero; on the first of `--forms`), and `--batching` the batch sizes
of `--batch` against each other (a target's time, calls in turn). `--profile` also writes ONNX Runtime's per-node profile
of one call per way and prints the time per operator type, which is where the exact speed-ups are
found. `--gemm` times instead the decoder's large matrix products alone, one by one at their shapes
for T context frames and B = 1: a one-MatMul ONNX graph whose weight is an initializer (prepacked by
MLAS, as the decoder's are) against `torch.nn.functional.linear` (MKL, as the mirror's `nn.Linear`),
in GFLOP/s: how fast each library multiplies on this CPU, apart from everything else.

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
import onnx
import onnxruntime as ort
import torch
from onnx import TensorProto, helper, numpy_helper

from c4g.model.attention import fused_export
from c4g.model.decoder import split_query_projection
from c4g.package.export import DECODER_FORMS, _config, build_model, export_plain_decoder, export_precomputed_decoder

# The graphs the bench can time: the export's two decoder forms, and the precomputed one as the
# export wrote it before the last layer's qkv projection was split (one product, q for every row).
GRAPHS = (*DECODER_FORMS, "precomputed-unsplit")


def session_options(
    profile_dir: Path | None = None, arena: bool = False, spinning: bool = True, denormal_as_zero: bool = False
) -> ort.SessionOptions:
    """Session settings: c4g-runtime's defaults (ONNX Runtime's: CPU arena off, threads spinning,
    default thread count), or the `C4G_CPU_ARENA` / `C4G_INTRA_OP_SPINNING` ones asked for (the
    engine's default is arena on, spinning off);
    `denormal_as_zero` sets ONNX Runtime's `session.set_denormal_as_zero` (not an engine setting)."""
    options = ort.SessionOptions()
    options.enable_cpu_mem_arena = arena
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spinning else "0")
    if denormal_as_zero:
        options.add_session_config_entry("session.set_denormal_as_zero", "1")
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
    "ONNX Runtime's defaults (no arena, spinning)": (False, True, False),
    "C4G_CPU_ARENA=true": (True, True, False),
    "C4G_INTRA_OP_SPINNING=false": (False, False, False),
    "both (the engine's default)": (True, False, False),
    "both + denormals as zero": (True, False, True),
}


def compare_settings(path: Path, projection: Path | None, cfg, args) -> None:
    """One session per setting, timed call by call in turn (median of `--repeats` each)."""
    sessions = {
        name: ort.InferenceSession(str(path), session_options(None, *setting), providers=["CPUExecutionProvider"])
        for name, setting in SETTINGS.items()
    }
    project = None if projection is None else ort.InferenceSession(str(projection), session_options(), providers=["CPUExecutionProvider"])
    for frames in args.frames:
        for batch in args.batch:
            feeds = inputs(cfg, frames, batch)
            if project is not None:
                (feeds["context_projection"],) = project.run(None, {"features": feeds["features"]})
            for s in sessions.values():
                s.run(None, feeds)
            times: dict[str, list[float]] = {name: [] for name in sessions}
            for _ in range(args.repeats):
                for name, s in sessions.items():
                    t = time.perf_counter()
                    s.run(None, feeds)
                    times[name].append(time.perf_counter() - t)
            print(f"T={frames} B={batch}: " + ", ".join(f"{k} {statistics.median(v) * 1e3:.2f} ms" for k, v in times.items()), flush=True)


# The ONNX Runtime ways the bench times: (name, graph, arena, spinning).
WAYS = [
    ("plain", "plain", False, True),
    ("precomputed unsplit, arena on, spinning off", "precomputed-unsplit", True, False),
    ("precomputed", "precomputed", False, True),
    ("precomputed, arena on, spinning off", "precomputed", True, False),
]


def export_forms(model, forms: list[str], tmp: Path) -> dict[str, tuple[Path, Path | None]]:
    """The decoder graph of each form (and the precomputed form's context projection graph)."""
    paths = {}
    with torch.no_grad(), fused_export(True):
        for form in forms:
            decoder = tmp / f"decoder-{form}.onnx"
            if form == "plain":
                export_plain_decoder(model, decoder)
                paths[form] = (decoder, None)
            else:
                with split_query_projection(form == "precomputed"):
                    export_precomputed_decoder(model, decoder, tmp / "context_projection.onnx")
                paths[form] = (decoder, tmp / "context_projection.onnx")
    return paths


def print_profile(path: Path, feeds: dict, args, arena: bool, spinning: bool) -> None:
    args.profile.mkdir(parents=True, exist_ok=True)
    prof = ort.InferenceSession(str(path), session_options(args.profile, arena, spinning), providers=["CPUExecutionProvider"])
    prof.run(None, feeds)
    prof.run(None, feeds)
    ops = per_op(Path(prof.end_profiling()))
    total = sum(ops.values())
    print("  per operator (ms, 2 calls): " + ", ".join(f"{k} {v:.0f} ({v / total:.0%})" for k, v in list(ops.items())[:8]))


def gemm_shapes(cfg, frames: int) -> list[tuple[str, int, int, int]]:
    """The exported decoder's large matrix products at B = 1 as (what, rows, inner dimension,
    columns): the first layer on every token (its qkv is the context projection's, once per clip),
    the last on the query rows except for its keys and values."""
    tokens, queries = frames * cfg.tokens_per_frame + cfg.queries, cfg.queries
    d, inner, mlp = cfg.decoder_dim, cfg.decoder_heads * cfg.decoder_head_dim, cfg.decoder_mlp
    return [
        ("layer 1 to_out", tokens, inner, d),
        ("layer 1 MLP up", tokens, d, mlp),
        ("layer 1 MLP down", tokens, mlp, d),
        ("layer 2 q", queries, d, inner),
        ("layer 2 k", tokens, d, inner),
        ("layer 2 v", tokens, d, inner),
        ("layer 2 to_out", queries, inner, d),
        ("layer 2 MLP up", queries, d, mlp),
        ("layer 2 MLP down", queries, mlp, d),
    ]


def matmul_graph(path: Path, weight: np.ndarray) -> None:
    """x [1, M, K] @ weight [K, N] as one ONNX MatMul with the weight an initializer."""
    k, n = weight.shape
    graph = helper.make_graph(
        [helper.make_node("MatMul", ["x", "w"], ["y"])],
        "gemm",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, "M", k])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, "M", n])],
        [numpy_helper.from_array(weight, "w")],
    )
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)], ir_version=10), str(path))


def compare_gemm(cfg, args, tmp: Path) -> list[dict]:
    """Each of the decoder's large products, ONNX Runtime (MLAS) against PyTorch (MKL), alternating."""
    rng = np.random.default_rng(0)
    rows = []
    for frames in args.frames:
        totals = {"onnxruntime": 0.0, "pytorch": 0.0, "gflop": 0.0}
        for what, m, k, n in gemm_shapes(cfg, frames):
            x = rng.standard_normal((1, m, k), dtype=np.float32)
            w = (rng.standard_normal((k, n), dtype=np.float32) / np.sqrt(k)).astype(np.float32)
            path = tmp / "gemm.onnx"
            matmul_graph(path, w)
            session = ort.InferenceSession(str(path), session_options(None, args.arena, not args.no_spinning), providers=["CPUExecutionProvider"])
            xt, wt = torch.from_numpy(x), torch.from_numpy(np.ascontiguousarray(w.T))
            times = {"onnxruntime": [], "pytorch": []}
            with torch.inference_mode():
                for _ in range(1 + args.repeats):
                    t = time.perf_counter()
                    (y,) = session.run(None, {"x": x})
                    times["onnxruntime"].append(time.perf_counter() - t)
                    t = time.perf_counter()
                    yt = torch.nn.functional.linear(xt, wt)
                    times["pytorch"].append(time.perf_counter() - t)
            gflop = 2.0 * m * k * n / 1e9
            best = {name: min(v[1:]) for name, v in times.items()}
            diff = float(np.abs(y - yt.numpy()).max())
            for name in best:
                totals[name] += best[name]
            totals["gflop"] += gflop
            rows.append({"frames": frames, "what": what, "m": m, "k": k, "n": n, "gflop": gflop, **{f"{k_}_s": v for k_, v in best.items()}})
            print(
                f"T={frames:3d} {what:17s} [{m} x {k}] @ [{k} x {n}] {gflop:6.1f} GFLOP: onnxruntime {gflop / best['onnxruntime']:6.1f} GFLOP/s, "
                f"pytorch {gflop / best['pytorch']:6.1f} GFLOP/s, ratio {best['onnxruntime'] / best['pytorch']:.2f} (differ by {diff:.1e})",
                flush=True,
            )
        print(
            f"T={frames:3d} all {totals['gflop']:.0f} GFLOP: onnxruntime {totals['onnxruntime']:.2f} s ({totals['gflop'] / totals['onnxruntime']:.1f} GFLOP/s), "
            f"pytorch {totals['pytorch']:.2f} s ({totals['gflop'] / totals['pytorch']:.1f} GFLOP/s), ratio {totals['onnxruntime'] / totals['pytorch']:.2f}",
            flush=True,
        )
    return rows


def compare_batches(paths: dict[str, tuple[Path, Path | None]], cfg, args) -> None:
    """The first of `--forms` with the arena on and spinning off, one call per batch size of
    `--batch` in turn, so that load from elsewhere reaches every size alike: seconds a target."""
    decoder, projection = paths[args.forms[0]]
    session = ort.InferenceSession(str(decoder), session_options(None, True, False), providers=["CPUExecutionProvider"])
    project = None if projection is None else ort.InferenceSession(str(projection), session_options(), providers=["CPUExecutionProvider"])
    for frames in args.frames:
        feeds = {batch: inputs(cfg, frames, batch) for batch in args.batch}
        if project is not None:
            (context_projection,) = project.run(None, {"features": feeds[args.batch[0]]["features"]})
            for f in feeds.values():
                f["context_projection"] = context_projection
        times: dict[int, list[float]] = {batch: [] for batch in args.batch}
        for _ in range(1 + args.repeats):
            for batch, f in feeds.items():
                t = time.perf_counter()
                session.run(None, f)
                times[batch].append((time.perf_counter() - t) / batch)
        one = statistics.median(times[args.batch[0]][1:])
        print(
            f"T={frames:3d} {args.forms[0]}, arena on, spinning off, seconds a target: "
            + ", ".join(f"B={b} {statistics.median(v[1:]):.3f} s ({statistics.median(v[1:]) / one:.2f})" for b, v in times.items()),
            flush=True,
        )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.decoder", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="official")
    ap.add_argument("--frames", type=int, nargs="+", default=[4, 16])
    ap.add_argument("--batch", type=int, nargs="+", default=[1])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--forms",
        nargs="+",
        choices=GRAPHS,
        default=["plain", "precomputed"],
        help="decoder graphs to time (precomputed-unsplit: the precomputed form with the last layer's qkv as one product)",
    )
    ap.add_argument(
        "--settings",
        action="store_true",
        help="instead of PyTorch, compare ONNX Runtime's session settings: its defaults, arena on, spinning off, both (the engine's default)",
    )
    ap.add_argument("--profile", type=Path, help="write an ONNX Runtime profile of one call per way here")
    ap.add_argument(
        "--batching",
        action="store_true",
        help="instead, time a target at each batch size of --batch, calls in turn (the first of --forms, arena on, spinning off)",
    )
    ap.add_argument("--gemm", action="store_true", help="instead, time the decoder's large matrix products alone in both libraries (best of --repeats)")
    ap.add_argument("--arena", action="store_true", help="with --gemm: ONNX Runtime's CPU arena on")
    ap.add_argument("--no-spinning", action="store_true", help="with --gemm: ONNX Runtime's threads do not spin")
    ap.add_argument("--json", type=Path, help="also write the results as JSON")
    args = ap.parse_args(argv)
    threads = os.cpu_count() or 1
    torch.set_num_threads(threads)
    cfg = _config(args.config, 0)
    if args.gemm:
        with tempfile.TemporaryDirectory() as tmp:
            rows = compare_gemm(cfg, args, Path(tmp))
        if args.json:
            args.json.write_text(json.dumps({"config": args.config, "threads": threads, "gemm": rows}, indent=2) + "\n")
        return 0
    t0 = time.perf_counter()
    model = build_model(cfg, seed=0, checkpoint=None)
    print(f"model: {args.config}, {sum(p.numel() for p in model.parameters()):,} parameters ({time.perf_counter() - t0:.0f} s to build)", flush=True)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        paths = export_forms(model, args.forms, Path(tmp))
        if args.settings:
            del model
            compare_settings(*paths[args.forms[0]], cfg, args)
            return 0
        if args.batching:
            del model
            compare_batches(paths, cfg, args)
            return 0
        cpu = ["CPUExecutionProvider"]
        ways = [w for w in WAYS if w[1] in args.forms]
        sessions = {name: ort.InferenceSession(str(paths[form][0]), session_options(None, arena, spinning), providers=cpu) for name, form, arena, spinning in ways}
        projection = next((p for _, p in paths.values() if p is not None), None)
        project = None if projection is None else ort.InferenceSession(str(projection), session_options(), providers=cpu)
        for frames in args.frames:
            for batch in args.batch:
                feeds = inputs(cfg, frames, batch)
                tensors = {k: torch.from_numpy(v) for k, v in feeds.items()}
                row = {"frames": frames, "batch": batch}
                form_feeds = {"plain": feeds}
                if project is not None:
                    t = time.perf_counter()
                    (context_projection,) = project.run(None, {"features": feeds["features"]})
                    row["context_projection_s"] = time.perf_counter() - t
                    form_feeds["precomputed"] = form_feeds["precomputed-unsplit"] = {**feeds, "context_projection": context_projection}
                times: dict[str, list[float]] = {name: [] for name in [*sessions, "pytorch"]}
                outputs = {}
                with torch.inference_mode():
                    # Warm-up (first-run allocations, prepacking), then the calls in turn.
                    for _ in range(1 + args.repeats):
                        for name, form, _, _ in ways:
                            t = time.perf_counter()
                            (outputs[name],) = sessions[name].run(None, form_feeds[form])
                            times[name].append(time.perf_counter() - t)
                        t = time.perf_counter()
                        outputs["pytorch"] = model.decode_canonical(*tensors.values()).numpy()
                        times["pytorch"].append(time.perf_counter() - t)
                pytorch_s = statistics.median(times["pytorch"][1:])
                row["pytorch_s"] = pytorch_s
                row["onnxruntime"] = {
                    name: {
                        "seconds": statistics.median(times[name][1:]),
                        "ratio": statistics.median(times[name][1:]) / pytorch_s,
                        "max_abs_diff": float(np.abs(outputs[name] - outputs["pytorch"]).max()),
                    }
                    for name in sessions
                }  # fmt: skip
                results.append(row)
                projected = f", context projection once {row['context_projection_s']:.3f} s" if "context_projection_s" in row else ""
                print(f"T={frames:3d} B={batch}: pytorch {pytorch_s:.3f} s{projected}", flush=True)
                for name, r in row["onnxruntime"].items():
                    print(
                        f"  onnxruntime {name}: {r['seconds']:.3f} s ({r['seconds'] / batch:.3f} s a target), "
                        f"ratio {r['ratio']:.2f}, outputs differ by {r['max_abs_diff']:.1e}",
                        flush=True,
                    )
                if args.profile:
                    for name, form, arena, spinning in ways:
                        print(f"  profile of {name}:")
                        print_profile(paths[form][0], form_feeds[form], args, arena, spinning)
    if args.json:
        args.json.write_text(json.dumps({"config": args.config, "threads": threads, "results": results}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
