"""Where keyframe interpolation goes wrong on a random-weight C4G decoder, and what placing the
keyframes differently would gain: a study for the official-size keyframes bench
(docs/tradeoffs.md, "Keyframes at the official decoder's size"), cheap enough for a CPU.

    python -m c4g.bench.keyframe_placement [--config official-small] [--frames 16] [--outputs 64] [--keyframes 8]

A random decoder of `--config`'s size (c4g.model.init.random_init, seed 0) is fed random context features
(T frames, source frames 0, 2, ..., 2(T - 1) of a 30 fps clip) and decoded exactly at `--outputs`
times evenly over the span, with the frame-step time policy (what official-layout packages use).
Then each placement's keyframes (a subset of those times) are interpolated at every output time with
the engine's position cubic (Hermite with Bessel tangents; the engine's breaks at context times are
left out) and compared with the exact positions: the mean distance over Gaussians, per output frame.

Placements: `uniform` (evenly over the outputs, both ends: the engine's `count`) and `geometric` (the
first output, then evenly in log(t - m) from one source step after the first context time m to the
end). Why geometric is worth trying: for every target at least a source step s after m the policy maps
context time t to (t - m) / (target - m), so in the first few steps every context frame's normalised
time changes by large factors (30 → 15 → 10 for a 1 s span at s = 1/30 s), and the time embedding's
sinusoids turn by radians per output frame; uniform steps in log(target - m) change them by equal
factors. A trained model maps those inputs onto a scene that moves smoothly in real time, so this says
what random weights do; what trained weights do needs them.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np
import torch

from c4g.model.config import PRESETS
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.model.time_policy import normalise

FPS = 30.0


def exact_positions(config: str, frames: int, outputs: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, list[float]]:
    """(output times [K], means [K, N, 3], context times) of a random decoder, frame-step policy."""
    cfg = PRESETS[config]
    model = C4G(cfg).eval()
    random_init(model, seed)
    tokens = (cfg.image_size // cfg.patch) ** 2
    features = torch.randn(frames, tokens, cfg.decoder_dim, generator=torch.Generator().manual_seed(seed + 1))
    context = [2 * i / FPS for i in range(frames)]
    times = np.linspace(context[0], context[-1], outputs)
    means = []
    with torch.no_grad():
        for t in times:
            ctx, tgt = normalise(context, float(t), "frame-step", 1 / FPS)
            means.append(model.decode(features, torch.tensor(ctx)[None], torch.tensor([tgt]))["means"][0].numpy())
    return times, np.stack(means).astype(np.float64), context


def bessel_interpolate(kt: np.ndarray, kv: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Piecewise cubic Hermite through (kt, kv) with Bessel tangents (the parabola through each
    keyframe and its neighbours), as engine/src/keyframes.rs interpolates positions."""
    h, d = np.diff(kt), np.diff(kv, axis=0) / np.diff(kt)[:, None, None]
    tangents = np.empty_like(kv)
    if len(kt) == 2:
        tangents[:] = d[0]
    else:
        tangents[1:-1] = (h[1:, None, None] * d[:-1] + h[:-1, None, None] * d[1:]) / (h[:-1] + h[1:])[:, None, None]
        # At the ends, the slope of the parabola through the last three keyframes at its end.
        tangents[0] = ((2 * h[0] + h[1]) * d[0] - h[0] * d[1]) / (h[0] + h[1])
        tangents[-1] = ((2 * h[-1] + h[-2]) * d[-1] - h[-1] * d[-2]) / (h[-1] + h[-2])
    out = np.empty((len(t),) + kv.shape[1:])
    for j, x in enumerate(t):
        i = min(max(int(np.searchsorted(kt, x, side="right")) - 1, 0), len(kt) - 2)
        u, w = (x - kt[i]) / h[i], h[i]
        out[j] = (
            (2 * u**3 - 3 * u**2 + 1) * kv[i]
            + (u**3 - 2 * u**2 + u) * w * tangents[i]
            + (-2 * u**3 + 3 * u**2) * kv[i + 1]
            + (u**3 - u**2) * w * tangents[i + 1]
        )
    return out


def placements(times: np.ndarray, context: list[float], n: int) -> dict[str, list[int]]:
    k = len(times)
    m = context[0]
    first = int(np.searchsorted(times, m + 1 / FPS))
    geometric = np.geomspace(times[first] - m, times[-1] - m, n - 1) + m
    return {
        "uniform": sorted({int(round(i)) for i in np.linspace(0, k - 1, n)}),
        "geometric": sorted({0, *(int(np.argmin(np.abs(times - g))) for g in geometric)}),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", default="official-small", choices=sorted(PRESETS))
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--outputs", type=int, default=64)
    parser.add_argument("--keyframes", type=int, default=8)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    times, means, context = exact_positions(args.config, args.frames, args.outputs)
    motion = np.linalg.norm(np.diff(means, axis=0), axis=-1).mean(axis=1)
    head = args.outputs // 8
    result = {"motion_per_step": {"first": [round(float(x), 4) for x in motion[:head]], "median": float(np.median(motion))}}
    for name, idx in placements(times, context, args.keyframes).items():
        err = np.linalg.norm(bessel_interpolate(times[idx], means[idx], times) - means, axis=-1).mean(axis=1)
        result[name] = {
            "keyframes": idx,
            "mean": float(err.mean()),
            "max": float(err.max()),
            "worst_frame": int(err.argmax()),
            f"mean_first_{head}": float(err[:head].mean()),
            "mean_rest": float(err[head:].mean()),
        }
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
