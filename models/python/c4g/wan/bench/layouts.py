"""Tokens and time per denoising step of C4G's refinement layout against VACE's, for the same frames.

    python -m c4g.wan.bench.layouts --config tiny --ort      # tiny: ONNX Runtime on graphs exported here
    python -m c4g.wan.bench.layouts --config 1.3b            # 1.3B dimensions: PyTorch eager (random weights)

Same frames means K context frames and n rendered frames. VACE's layout puts them in one video, padded to
4k + 1 frames and encoded as one chunk: (K + n - 1) / 4 + 1 latent frames (rounded up). C4G's gives each
keyframe its own latent frame and the rendered frames (padded to 4k + 1) one chunk: K + (n - 1) / 4 + 1.
A step is two transformer runs (classifier-free guidance); the sampler's arithmetic is negligible beside
them and left out. Beside the times, PyTorch's FLOP counter gives each step's operations on the meta
device: the ratio that does not depend on a shared machine's load. Defaults are C4G's training window (12 keyframes, 23 rendered frames) at 64 x 64, a
small video that the 1.3B transformer runs on a CPU in seconds per call.

At the 1.3B dimensions the transformer is timed in PyTorch (diffusers' modules, f32): exporting 8.6 GB
of weights per layout to time ONNX Runtime is out of reach of a development machine; the tiny size is
timed in both.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import torch

from c4g.wan import c4g_layout, onnx_graphs
from c4g.wan.configs import PRESETS, RefinerConfig, build_transformer


def pad_to_chunk(frames: int) -> int:
    """The smallest 4k + 1 >= frames."""
    return frames + (-(frames - 1)) % 4


def layouts(keyframes: int, rendered: int) -> dict[str, dict]:
    vace_frames = pad_to_chunk(keyframes + rendered)
    chunk = pad_to_chunk(rendered)
    return {
        "vace": {"video_frames": vace_frames, "latent_frames": (vace_frames - 1) // 4 + 1, "keyframes": 0},
        "c4g": {"video_frames": chunk, "latent_frames": keyframes + (chunk - 1) // 4 + 1, "keyframes": keyframes},
    }


def inputs(cfg: RefinerConfig, latent_frames: int, keyframes: int, text_tokens: int) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(0)
    h, w = cfg.height // 8, cfg.width // 8
    t = cfg.transformer
    rendered_latents = latent_frames - keyframes
    return {
        "latents": torch.randn(1, 16, latent_frames, h, w, generator=gen),
        "timestep": torch.tensor([937.5]),
        "text_embeddings": torch.randn(1, text_tokens, t["text_dim"], generator=gen),
        "control": torch.randn(1, t["vace_in_channels"], latent_frames, h, w, generator=gen),
        "control_scale": torch.ones(len(t["vace_layers"])),
        "positions": c4g_layout.positions(list(range(0, 2 * keyframes, 2)), rendered_latents) if keyframes else torch.arange(latent_frames),
    }


def interleaved_medians(runs: dict[str, callable], repeats: int) -> dict[str, float]:
    """Median seconds of each run, timed in turns (A B A B ...) after one warm-up each, so that a
    shared machine's load drifts over both alike."""
    for run in runs.values():
        run()  # warm-up: allocations, ONNX Runtime's first-run planning
    times: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(t) for name, t in times.items()}


@torch.no_grad()
def flops_per_call(cfg: RefinerConfig, feeds: dict[str, torch.Tensor]) -> int:
    """Floating-point operations of one transformer run, counted by PyTorch on the meta device (no
    weights, no time): the machine-independent measure of the work."""
    from torch.utils.flop_counter import FlopCounterMode

    model = build_transformer(cfg.transformer, device="meta")
    meta = {k: v.to("meta") for k, v in feeds.items()}
    counter = FlopCounterMode(display=False)
    with counter:
        c4g_layout.velocity(model, meta["latents"], 937.5, meta["text_embeddings"], meta["control"], meta["positions"])
    return counter.get_total_flops()


def pytorch_run(transformer, feeds: dict[str, torch.Tensor]):
    @torch.no_grad()
    def run():
        c4g_layout.velocity(
            transformer, feeds["latents"], float(feeds["timestep"][0]), feeds["text_embeddings"], feeds["control"], feeds["positions"]
        )

    return run


def ort_run(transformer, cfg: RefinerConfig, feeds: dict[str, torch.Tensor], threads: int):
    import onnxruntime as ort

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "transformer.onnx"
        onnx_graphs.export_transformer(transformer, cfg, path, fused=True)
        options = ort.SessionOptions()
        options.log_severity_level = 3
        options.intra_op_num_threads = threads
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    numpy_feeds = {k: v.numpy() for k, v in feeds.items()}
    return lambda: session.run(None, numpy_feeds)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", choices=sorted(PRESETS), default="tiny")
    parser.add_argument("--keyframes", type=int, default=12)
    parser.add_argument("--rendered", type=int, default=23)
    parser.add_argument("--height", type=int, default=64)
    parser.add_argument("--width", type=int, default=64)
    parser.add_argument("--text-tokens", type=int, default=None, help="default: the config's (512 at 1.3B)")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--ort", action="store_true", help="also time ONNX Runtime on graphs exported here (tiny sizes)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    base = PRESETS[args.config]
    text_tokens = args.text_tokens or base.text_tokens
    transformer = build_transformer(base.transformer, seed=0)
    rows, runs = [], {}
    for name, layout in layouts(args.keyframes, args.rendered).items():
        cfg = RefinerConfig(
            name=f"bench-{name}", transformer=base.transformer, vae=base.vae, frames=layout["video_frames"],
            height=args.height, width=args.width, text_tokens=text_tokens, keyframes=layout["keyframes"],
        )  # fmt: skip
        feeds = inputs(cfg, cfg.latent_frames, layout["keyframes"], text_tokens)
        rows.append({"layout": name, "latent_frames": cfg.latent_frames, "tokens": cfg.tokens, "gflop_per_step": 2 * flops_per_call(cfg, feeds) / 1e9})
        runs[f"{name} pytorch"] = pytorch_run(transformer, feeds)
        if args.ort:
            runs[f"{name} ort"] = ort_run(transformer, cfg, feeds, args.threads)
    medians = interleaved_medians(runs, args.repeats)
    for row in rows:
        for engine in ("pytorch", "ort"):
            if f"{row['layout']} {engine}" in medians:
                row[f"{engine}_s_per_step"] = 2 * medians[f"{row['layout']} {engine}"]
        print(json.dumps(row), flush=True)
    vace, c4g = rows
    ratio = {k: c4g[k] / vace[k] for k in vace if k.endswith("per_step") or k == "tokens"}
    print(json.dumps({"config": args.config, "keyframes": args.keyframes, "rendered": args.rendered, "size": [args.height, args.width], "c4g_over_vace": ratio}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
