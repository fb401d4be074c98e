"""The speed/accuracy trade on a GPU, through the PyTorch mirror (docs/tradeoffs.md, "On a GPU").

    python -m c4g.bench.gpu_tradeoffs [--device cuda] [--markdown FILE] [--json FILE]
    python -m c4g.bench.gpu_tradeoffs --device cpu --small     # checks the harness where there is no GPU

Why the mirror and not ONNX Runtime: the GPU machine we are lent has a CPU-only onnxruntime, and
the CUDA provider's wheel and libraries do not fit in what a call can carry, so the CUDA-provider
table the issue asks for cannot be made there. The mirror computes what the packages compute (the
parity tests hold them to 1e-4), so its times are the bar an ONNX CUDA path must reach, and its
precision errors are the ones a reduced-precision GPU path would have.

Tables, all in one run:
1. **Settings** at the official decoder's size, random weights (cost does not depend on the values;
   fidelity does, see docs/tradeoffs.md), a one-block encoder (the decoder is the official one; the
   encoder only gives it features of its width), T = 16 context frames (source frames 0, 2, ..., 30
   of a 30 fps clip), `--outputs` times evenly over the span, the frame-step time policy (what
   official-layout packages declare). Exact decodes in f32 (TF32 off: the reference), TF32, bf16
   and f16; keyframes, exact f32 sets at a subset of the output times interpolated as the engine
   interpolates (`interpolate`): uniform counts of 16 (`balanced`: one a context spacing), 11
   (`fast`: 1.5 spacings), 8 and 4, and 8 spaced in log(t - m) (`c4g.bench.keyframe_placement`'s
   geometric placement); and 8 uniform keyframes decoded in f16. Each row: decoder calls and
   exact sets, decode ms a frame (decoder calls in batches of `--batch` plus the interpolation,
   median of `--repeats`), render ms a frame, bytes a frame on the wire, peak GPU memory, and
   against the f32 exact renders (the first context camera and a novel one, every output time):
   PSNR pooled over all frames, the worst frame's PSNR, and the largest and mean position error.
2. **Context frames and batch**: decode ms a target at T = 2, 4, 8, 16 and B = 1, 16, each dtype.
3. **Query dropping**: decode ms a target keeping 2048, 1024, 512 and 256 of the queries (evenly
   spaced), and how far the kept Gaussians move against the full decode (f32).
4. **c4g-tiny's size**: decode ms a target (T = 4, B = 1 and 16) and render ms at 64 px, random
   weights: what the default model costs on this GPU. Its quality against ground truth is the CPU
   table's (the same computation up to rounding); its f16 error is measured here on random weights.

Renders use the dense PyTorch rasterizer (`c4g.raster.dense`, the 3-sigma footprint) on the
device; the wgpu rasterizer's GPU numbers are scripts/device-check's part 2. Interpolation runs on
the device in float64 (the engine interpolates on the CPU; its cost is under 1 % of a decode).
"""

from __future__ import annotations

import argparse
import copy
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

from c4g.model.config import OFFICIAL, OFFICIAL_SMALL, C4GConfig
from c4g.model.decoder import to_canonical
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.model.query_subset import decode_canonical_subset
from c4g.model.time_policy import normalise
from c4g.raster.dense import render
from c4g.train.synthetic import C4G_FOCAL

from .gpu import timed

FPS = 30.0
DTYPES = {"fp32": torch.float32, "tf32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}
WIRE_BYTES = {"fp32": 4, "tf32": 4, "bf16": 2, "fp16": 2}  # a channel on the wire (bf16 goes as f16)


def one_block(cfg: C4GConfig) -> C4GConfig:
    return C4GConfig.from_dict({**cfg.to_dict(), "dino_depth": 1, "aggregator_depth": 1})


def built(cfg: C4GConfig, device: torch.device, seed: int = 0) -> C4G:
    model = C4G(cfg).eval()
    random_init(model, seed)
    return model.to(device)


class Precisions:
    """The model in each dtype: copies of the f32 one, made once (casting one model down and back
    up would round its weights)."""

    def __init__(self, model: C4G):
        self.models = {torch.float32: model}

    def __call__(self, dtype: torch.dtype) -> C4G:
        if dtype not in self.models:
            self.models[dtype] = copy.deepcopy(self.models[torch.float32]).to(dtype)
        return self.models[dtype]


class Clock:
    """Median seconds of a call after two warm-ups (`bench_gpu.timed`: CUDA events on a GPU, the
    wall clock elsewhere)."""

    def __init__(self, device: torch.device, repeats: int):
        self.device, self.repeats = device, repeats

    def __call__(self, fn) -> float:
        return timed(fn, self.device, self.repeats)


def set_tf32(on: bool) -> None:
    torch.backends.cuda.matmul.allow_tf32 = on
    torch.backends.cudnn.allow_tf32 = on


# -- keyframe interpolation, as engine/src/keyframes.rs does it -------------------------------------


def _segments(kt: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    i = (torch.searchsorted(kt, t, right=True) - 1).clamp(0, len(kt) - 2)
    return i, (t - kt[i]) / (kt[i + 1] - kt[i])


def bessel_tangents(kt: torch.Tensor, kv: torch.Tensor) -> torch.Tensor:
    """Each keyframe's tangent: the slope of the parabola through it and its neighbours; at the
    ends, of the parabola through the last three (the two keyframes' chord when there are two)."""
    h = kt.diff()
    d = kv.diff(dim=0) / h.reshape(-1, *[1] * (kv.ndim - 1))
    if len(kt) == 2:
        return torch.stack((d[0], d[0]))
    hh = lambda x: x.reshape(-1, *[1] * (kv.ndim - 1))  # noqa: E731
    inner = (hh(h[1:]) * d[:-1] + hh(h[:-1]) * d[1:]) / hh(h[:-1] + h[1:])
    first = ((2 * h[0] + h[1]) * d[0] - h[0] * d[1]) / (h[0] + h[1])
    last = ((2 * h[-1] + h[-2]) * d[-1] - h[-1] * d[-2]) / (h[-1] + h[-2])
    return torch.cat((first[None], inner, last[None]))


def slerp(q0: torch.Tensor, q1: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """Unit quaternions [..., 4] along the shortest arc, `u` [...] in [0, 1]; nearly equal ones are
    blended linearly and renormalised (where sin θ would lose the angle)."""
    q0 = q0 / q0.norm(dim=-1, keepdim=True)
    q1 = q1 / q1.norm(dim=-1, keepdim=True)
    dot = (q0 * q1).sum(-1)
    q1 = torch.where(dot[..., None] < 0, -q1, q1)
    dot = dot.abs().clamp(max=1.0)
    theta = torch.acos(dot)
    s = torch.sin(theta)
    near = dot > 0.9995
    safe = torch.where(near, torch.ones_like(s), s)
    w0 = torch.where(near, 1 - u, torch.sin((1 - u) * theta) / safe)
    w1 = torch.where(near, u, torch.sin(u * theta) / safe)
    q = w0[..., None] * q0 + w1[..., None] * q1
    return q / q.norm(dim=-1, keepdim=True)


def interpolate(kt: torch.Tensor, sets: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Canonical sets [K, N, 14] at keyframe times `kt` [K] → sets [M, N, 14] at times `t` [M]:
    positions by a cubic Hermite with Bessel tangents, scales linearly in log space, rotations by
    slerp on the shortest arc, opacity and colour linearly (the engine's rules; its breaks at
    context times are left out)."""
    kt, t, sets = kt.double(), t.double(), sets.double()
    i, u = _segments(kt, t)
    h = (kt[i + 1] - kt[i])[:, None, None]
    uu = u[:, None, None]
    pos, tan = sets[..., 0:3], bessel_tangents(kt, sets[..., 0:3])
    positions = (
        (2 * uu**3 - 3 * uu**2 + 1) * pos[i]
        + (uu**3 - 2 * uu**2 + uu) * h * tan[i]
        + (-2 * uu**3 + 3 * uu**2) * pos[i + 1]
        + (uu**3 - uu**2) * h * tan[i + 1]
    )
    log_s = sets[..., 3:6].clamp_min(1e-30).log()
    scales = ((1 - uu) * log_s[i] + uu * log_s[i + 1]).exp()
    n = sets.shape[1]
    rotations = slerp(sets[i, :, 6:10], sets[i + 1, :, 6:10], u[:, None].expand(-1, n))
    rest = (1 - uu) * sets[i, :, 10:14] + uu * sets[i + 1, :, 10:14]
    return torch.cat((positions, scales, rotations, rest), dim=-1)


def placements(times: np.ndarray, m: float, step: float) -> dict[str, list[int]]:
    """Keyframe subsets of the output times (indices): uniform counts, and 8 in log(t - m)."""
    k = len(times)
    uniform = lambda n: sorted({int(round(x)) for x in np.linspace(0, k - 1, n)})  # noqa: E731
    first = int(np.searchsorted(times, m + step))
    geometric = np.geomspace(max(times[first] - m, step), times[-1] - m, 7) + m
    return {
        "balanced: 16 keyframes (one a context spacing)": uniform(16),
        "fast: 11 keyframes (1.5 context spacings)": uniform(11),
        "8 keyframes": uniform(8),
        "4 keyframes": uniform(4),
        "8 keyframes in log(t - m)": sorted({0, *(int(np.argmin(np.abs(times - g))) for g in geometric)}),
    }


# -- the measurements -------------------------------------------------------------------------------


class Clip:
    """A random-weight model's encoding of random frames, and the frame-step times of its outputs."""

    def __init__(self, model: C4G, frames: int, outputs: int, device: torch.device):
        gen = torch.Generator().manual_seed(1)
        size = model.cfg.image_size
        images = (torch.rand(frames, 3, size, size, generator=gen) * 2 - 1).to(device)
        with torch.no_grad():
            self.features = model.encode(images)
        self.context = [2 * i / FPS for i in range(frames)]
        self.times = np.linspace(self.context[0], self.context[-1], outputs)
        rows = [normalise(self.context, float(t), "frame-step", 1 / FPS) for t in self.times]
        self.ctx = torch.tensor(np.array([r[0] for r in rows]), dtype=torch.float32, device=device)
        self.tgt = torch.tensor([r[1] for r in rows], dtype=torch.float32, device=device)


def decode_sets(model: C4G, clip: Clip, which: list[int], batch: int, dtype: torch.dtype) -> torch.Tensor:
    """Canonical sets [len(which), N, 14] (f32) at the outputs `which`, `batch` targets a call."""
    features = clip.features.to(dtype)
    out = []
    with torch.no_grad():
        for start in range(0, len(which), batch):
            idx = torch.tensor(which[start : start + batch], device=features.device)
            out.append(model.decode_canonical(features, clip.ctx[idx].to(dtype), clip.tgt[idx].to(dtype)).float())
    return torch.cat(out)


def cameras(device: torch.device) -> list[torch.Tensor]:
    """The first context camera (the identity) and a novel one: moved (0.15, -0.05, 0.1), turned 6°
    about the vertical axis (as engine/benches/official_keyframes.rs renders)."""
    a = math.radians(6.0)
    novel = torch.eye(4, dtype=torch.float64)
    novel[:3, :3] = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=torch.float64)
    novel[:3, 3] = torch.tensor([0.15, -0.05, 0.1], dtype=torch.float64)
    return [torch.eye(4, dtype=torch.float32, device=device), novel.float().to(device)]


def render_set(g: torch.Tensor, pose: torch.Tensor, size: int) -> torch.Tensor:
    f = C4G_FOCAL * size
    g = g.float()
    out = render(g[:, 0:3], g[:, 3:6], g[:, 6:10], g[:, 10], g[:, 11:14], (f, f, size / 2, size / 2), pose, size, size)
    return out["rgb"].clamp(0, 1)


def renders(sets: torch.Tensor, poses: list[torch.Tensor], size: int) -> torch.Tensor:
    with torch.no_grad():
        return torch.stack([render_set(g, p, size) for p in poses for g in sets])


def psnr(mse: float) -> float:
    return math.inf if mse <= 0 else 10 * math.log10(1 / mse)


def fidelity(images: torch.Tensor, exact_images: torch.Tensor, sets: torch.Tensor, exact_sets: torch.Tensor) -> dict:
    per_frame = ((images.double() - exact_images.double()) ** 2).mean(dim=(1, 2, 3))
    err = (sets[..., 0:3].double() - exact_sets[..., 0:3].double()).norm(dim=-1)
    finite = bool(torch.isfinite(sets).all())
    return {
        "psnr_pooled": psnr(float(per_frame.mean())),
        "psnr_worst_frame": psnr(float(per_frame.max())),
        "position_error_max": float(err.max()),
        "position_error_mean": float(err.mean()),
        "finite": finite,
    }


def peak_memory(device: torch.device, fn) -> tuple[object, int | None]:
    if device.type != "cuda":
        return fn(), None
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats(device)
    value = fn()
    torch.cuda.synchronize()
    return value, torch.cuda.max_memory_allocated(device)


def settings_table(at: Precisions, clip: Clip, args, clock: Clock, device: torch.device) -> list[dict]:
    model = at(torch.float32)
    outputs = len(clip.times)
    everything = list(range(outputs))
    poses = cameras(device)
    n = model.cfg.queries
    set_tf32(False)
    exact = decode_sets(model, clip, everything, args.batch, torch.float32)
    exact_images = renders(exact, poses, args.render_size)
    render_ms = clock(lambda: render_set(exact[0], poses[1], args.render_size)) * 1e3
    t_out = torch.from_numpy(clip.times).to(device)
    rows = []

    def row(name: str, dtype_name: str, which: list[int]) -> None:
        dtype = DTYPES[dtype_name]
        set_tf32(dtype_name == "tf32")
        keyframed = len(which) < outputs

        def run() -> torch.Tensor:
            sets = decode_sets(at(dtype), clip, which, args.batch, dtype)
            return interpolate(t_out[which], sets, t_out).float() if keyframed else sets

        sets, memory = peak_memory(device, run)
        seconds = clock(run)
        set_tf32(False)
        images = renders(sets, poses, args.render_size)
        decode_ms = seconds * 1e3 / outputs
        rows.append(
            {
                "setting": name,
                "dtype": dtype_name,
                "exact_sets": len(which),
                "decoder_calls": math.ceil(len(which) / args.batch),
                "decode_ms_per_frame": decode_ms,
                "render_ms_per_frame": render_ms,
                "total_ms_per_frame": decode_ms + render_ms,
                "bytes_per_frame": n * 14 * WIRE_BYTES[dtype_name],
                "peak_memory_bytes": memory,
                **fidelity(images, exact_images, sets, exact),
            }
        )
        print(f"gpu_tradeoffs: {name} ({dtype_name}): {decode_ms:.3f} ms a frame", file=sys.stderr, flush=True)

    for dtype_name in ("fp32", "tf32", "bf16", "fp16"):
        row("exact", dtype_name, everything)
    step = 1 / FPS
    for name, which in placements(clip.times, clip.context[0], step).items():
        row(name, "fp32", which)
    row("8 keyframes", "fp16", placements(clip.times, clip.context[0], step)["8 keyframes"])
    return rows


def context_table(at: Precisions, args, clock: Clock, device: torch.device) -> list[dict]:
    rows = []
    for frames in args.context_frames:
        clip = Clip(at(torch.float32), frames, max(args.batches), device)
        for dtype_name in ("fp32", "bf16", "fp16"):
            dtype = DTYPES[dtype_name]
            for b in args.batches:
                which = list(range(b))
                ms = clock(lambda: decode_sets(at(dtype), clip, which, b, dtype)) * 1e3 / b
                rows.append({"frames": frames, "dtype": dtype_name, "batch": b, "decode_ms_per_target": ms})
    return rows


def queries_table(at: Precisions, clip: Clip, args, clock: Clock, device: torch.device) -> list[dict]:
    model, low = at(torch.float32), at(torch.bfloat16)
    n = model.cfg.queries
    b = max(args.batches)
    which = torch.arange(b, device=device)
    features = clip.features
    with torch.no_grad():
        full = model.decode_canonical(features, clip.ctx[which], clip.tgt[which])
    rows = []
    for kept in sorted({n, n // 2, n // 4, n // 8}, reverse=True):
        idx = torch.linspace(0, n - 1, kept, device=device).round().long()
        with torch.no_grad():
            part = decode_canonical_subset(model, features, clip.ctx[which], clip.tgt[which], idx)
        moved = (part[..., 0:3] - full[:, idx, 0:3]).norm(dim=-1)
        f16 = features.to(torch.bfloat16)
        c, t = clip.ctx[which].to(torch.bfloat16), clip.tgt[which].to(torch.bfloat16)

        def run(f16=f16, c=c, t=t, idx=idx):
            with torch.no_grad():
                return decode_canonical_subset(low, f16, c, t, idx)

        ms = clock(run) * 1e3 / b
        rows.append({"queries": kept, "decode_ms_per_target_bf16": ms, "moved_max": float(moved.max()), "moved_mean": float(moved.mean())})
    return rows


def tiny_table(args, clock: Clock, device: torch.device) -> list[dict]:
    from c4g.train.loop import TINY

    at = Precisions(built(TINY, device))
    model = at(torch.float32)
    clip = Clip(model, 4, max(args.batches), device)
    rows = []
    exact = decode_sets(model, clip, list(range(max(args.batches))), max(args.batches), torch.float32)
    render_ms = clock(lambda: render_set(exact[0], cameras(device)[1], TINY.image_size)) * 1e3
    for dtype_name in ("fp32", "fp16"):
        dtype = DTYPES[dtype_name]
        for b in args.batches:
            which = list(range(b))
            ms = clock(lambda: decode_sets(at(dtype), clip, which, b, dtype)) * 1e3 / b
            sets = decode_sets(at(dtype), clip, which, b, dtype)
            err = (sets[..., 0:3] - exact[:b, :, 0:3]).norm(dim=-1)
            rows.append(
                {
                    "dtype": dtype_name,
                    "batch": b,
                    "decode_ms_per_target": ms,
                    "render_ms_64px": render_ms,
                    "sets_per_second": 1e3 / ms,
                    "position_error_max": float(err.max()),
                }
            )
    return rows


def markdown(result: dict) -> str:
    fmt = lambda x, p=3: "∞ (identical)" if x == math.inf else f"{x:.{p}f}"  # noqa: E731
    mib = lambda b: "n/a" if b is None else f"{b / 2**20:.0f} MiB"  # noqa: E731
    lines = [
        f"**Device:** {result['device']}; PyTorch {result['torch']}; {result['config']} decoder dims, random weights, "
        f"one-block encoder; T = {result['frames']} context frames, {result['outputs']} outputs, frame-step policy; "
        f"decoder calls of {result['batch']} targets; renders {result['render_size']} px (dense PyTorch rasterizer); "
        f"median of {result['repeats']}; whole run {result['seconds']:.0f} s.",
        "",
        "| setting | dtype | exact sets (calls) | decode ms/frame | render ms/frame | total ms/frame | bytes/frame | peak GPU memory | PSNR vs exact f32, pooled | worst frame | position error max / mean |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in result["settings"]:
        finite = "" if r["finite"] else " (non-finite values!)"
        lines.append(
            f"| {r['setting']} | {r['dtype']} | {r['exact_sets']} ({r['decoder_calls']}) | {r['decode_ms_per_frame']:.3f} | "
            f"{r['render_ms_per_frame']:.3f} | {r['total_ms_per_frame']:.3f} | {r['bytes_per_frame']:,} | {mib(r['peak_memory_bytes'])} | "
            f"{fmt(r['psnr_pooled'], 2)}{finite} | {fmt(r['psnr_worst_frame'], 2)} | {r['position_error_max']:.2e} / {r['position_error_mean']:.2e} |"
        )
    lines += ["", "Decode time a target against context frames and batch:", "", "| T | dtype | B | ms a target |", "|---|---|---|---|"]
    lines += [f"| {r['frames']} | {r['dtype']} | {r['batch']} | {r['decode_ms_per_target']:.3f} |" for r in result["context"]]
    lines += ["", f"Query dropping (T = {result['frames']}, bf16, batches of {max(r['batch'] for r in result['context'])}):", "", "| queries kept | ms a target | kept Gaussians moved, max / mean (f32) |", "|---|---|---|"]
    lines += [f"| {r['queries']} | {r['decode_ms_per_target_bf16']:.3f} | {r['moved_max']:.3g} / {r['moved_mean']:.3g} |" for r in result["queries"]]
    lines += ["", "c4g-tiny's size (512 Gaussians, 64 px, T = 4), random weights:", "", "| dtype | B | ms a target | sets/s | render ms at 64 px | position error max against f32 at the largest B |", "|---|---|---|---|---|---|"]
    lines += [
        f"| {r['dtype']} | {r['batch']} | {r['decode_ms_per_target']:.3f} | {r['sets_per_second']:,.0f} | {r['render_ms_64px']:.3f} | {r['position_error_max']:.2e} |"
        for r in result["tiny"]
    ]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.gpu_tradeoffs", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--small", action="store_true", help="the official-small size, few outputs, small renders: a check of the harness on a CPU")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--outputs", type=int, default=64)
    ap.add_argument("--batch", type=int, default=16, help="targets a decoder call")
    ap.add_argument("--render-size", type=int, default=224)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--context-frames", type=int, nargs="+", default=[2, 4, 8, 16])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--markdown", type=Path)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    device = torch.device(args.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        print("gpu_tradeoffs: CUDA is not available (use --device cpu --small to check the harness)", file=sys.stderr)
        return 2
    if args.small:
        args.frames, args.outputs, args.render_size, args.repeats = min(args.frames, 4), min(args.outputs, 12), min(args.render_size, 24), 1
        args.context_frames, args.batches = [2, 4], [1, 4]
    started = time.time()
    torch.manual_seed(0)
    cfg = one_block(OFFICIAL_SMALL if args.small else OFFICIAL)
    at = Precisions(built(cfg, device))
    clock = Clock(device, args.repeats)
    clip = Clip(at(torch.float32), args.frames, args.outputs, device)
    result = {
        "device": torch.cuda.get_device_name(device) if device.type == "cuda" else "CPU",
        "torch": torch.__version__,
        "config": "official-small" if args.small else "official",
        "frames": args.frames,
        "outputs": args.outputs,
        "batch": args.batch,
        "render_size": args.render_size,
        "repeats": args.repeats,
    }
    result["settings"] = settings_table(at, clip, args, clock, device)
    result["queries"] = queries_table(at, clip, args, clock, device)
    result["context"] = context_table(at, args, clock, device)
    result["tiny"] = tiny_table(args, clock, device)
    result["seconds"] = time.time() - started
    text = markdown(result)
    print(text)
    if args.markdown:
        args.markdown.write_text(text)
    if args.json:
        args.json.write_text(json.dumps(result, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
