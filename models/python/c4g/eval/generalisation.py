"""Does a model package reconstruct 4D, or only its training generator? Scores on two worlds.

    python -m c4g.eval.generalisation --package models/c4g-tiny --clips 24 [--strides 2 4] [--out DIR]

The package runs as the service runs it (its ONNX graphs on ONNX Runtime's CPU provider, its
declared time policy), on clips of two procedural worlds: `train-world` (`c4g.train.synthetic`'s test
split: the generator c4g-tiny was trained on, other seeds) and `eval-world` (`c4g.eval.world`:
written separately, never trained on). Protocol per clip, at 64 x 64 and 10 fps, for each stride s:
4 context frames s source frames apart (0, s, 2s, 3s), targets half-way between neighbours:
- interpolated times: the model's render at the target's true camera, against the true frame.
  The true cameras are what the service calls given cameras, and the service fits their scale to
  the model's depth scale from the context frames alone (`fit_camera_scale`, the mirror of
  `c4g_renderer::align::fit_translation_scale`): *model* renders at cameras so fitted, *model,
  unfitted* at the convention's (first-to-last context camera distance 1) as they are;
- novel views: the same times from a camera moved off the path (`c4g.eval.held_out`'s NOVEL_OFFSET
  and NOVEL_YAW, in the model's units), against the scene rendered there;
- baselines: the mean colour of the context frames, the nearest context frame (the earlier of
  two equidistant ones), the average of the two neighbours; held as they are at novel views;
- ceilings (oracles: they see the true frame): the true frame with each of the package's query
  blocks averaged (each Gaussian starts as a splat of one such block, `c4g.train.loop.QUERY_GRID` a
  patch: what its Gaussians can draw when each covers its own block exactly), and with each patch
  averaged (what a model drawing patch-sized blobs can reach); the model's own render of the
  context frames it was given (*reconstructed*), against them: what it keeps of its input;
  the model's Gaussians at the *true depth scale* (scaled about the first camera, which leaves
  that camera's image as it is, so their median depth is the first frame's true median depth):
  what its geometry costs it beyond the scale (the model's Gaussians unfitted). The scale is
  printed too (`depth ratio`: the model's median depth over the truth's, geometric mean and range
  over the clips, as predicted and after the fit).
Inputs and truths are quantised to 8 bits first, as the service sees them; PSNR from
`c4g.raster.metrics`. Prints a Markdown table of mean PSNR (with the clip count) and writes
`generalisation.json` to `--out` when given.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from c4g.model.time_policy import normalise_batch
from c4g.raster.metrics import psnr
from c4g.train import synthetic
from c4g.train.loop import QUERY_GRID

from . import world as eval_world
from .held_out import novel_pose, novel_world_poses, quantise, render_gaussians

WORLDS = ("train-world", "eval-world")
METHODS = ("model", "model, unfitted", "mean colour", "nearest context frame", "blend of neighbours")
CEILINGS = ("true frame in query blocks", "true frame in patches", "model, reconstructed", "model at the true depth scale")
# The model's median depth over the truth's (first frame), as it predicts it and after the fit.
RATIOS = ("depth ratio", "depth ratio, fitted")


# The scale search, as the service's: camera-translation factors 2^(k/4) for k in this range, then
# a golden-section search on log2 of the factor between the best one's neighbours.
SCALE_STEPS = range(-24, 25)
SCALE_REFINEMENTS = 12
# A best factor that lowers the error by less than this fraction of factor 1's is no evidence:
# the cameras then keep the convention's scale (a clip with no parallax fits every factor).
SCALE_EVIDENCE = 1e-3


def fit_camera_scale(gaussians: np.ndarray, w2c: np.ndarray, frames: np.ndarray, size: int) -> float:
    """The factor on every camera's translation (camera centres scaled about the first camera's)
    that best matches Gaussians [V, N, 14], each decoded at its view's time, rendered at poses
    [V, 4, 4] against frames [V, H, W, 3]: least mean squared error. Multiplying the given cameras'
    translations by it is dividing the Gaussians' positions and sizes by it."""

    def cost(log2_factor: float) -> float:
        poses = w2c.copy()
        poses[:, :3, 3] *= 2.0**log2_factor
        return float(np.mean((render_gaussians(torch.from_numpy(gaussians), poses, size) - frames) ** 2))

    tried = {k / 4: cost(k / 4) for k in SCALE_STEPS}
    best = min(tried, key=tried.get)
    lo, hi = max(best - 0.25, SCALE_STEPS[0] / 4), min(best + 0.25, SCALE_STEPS[-1] / 4)
    golden = (np.sqrt(5) - 1) / 2
    a, b = hi - golden * (hi - lo), lo + golden * (hi - lo)
    fa, fb = cost(a), cost(b)
    for _ in range(SCALE_REFINEMENTS):
        if fa <= fb:
            hi, b, fb = b, a, fa
            a = hi - golden * (hi - lo)
            fa = cost(a)
        else:
            lo, a, fa = a, b, fb
            b = lo + golden * (hi - lo)
            fb = cost(b)
        tried[a], tried[b] = fa, fb
    best = min(tried, key=tried.get)
    return 1.0 if tried[best] >= tried[0.0] * (1 - SCALE_EVIDENCE) else float(2.0**best)


class Package:
    """A package's encoder and decoder on ONNX Runtime (CPU), as the engine runs them."""

    def __init__(self, path: Path):
        self.manifest = json.loads((path / "model.json").read_text())
        options = ort.SessionOptions()
        options.intra_op_num_threads = 0
        cpu = ["CPUExecutionProvider"]
        self.encoder = ort.InferenceSession(str(path / "encoder.onnx"), options, providers=cpu)
        self.decoder = ort.InferenceSession(str(path / "decoder.onnx"), options, providers=cpu)
        projection = path / "context_projection.onnx"
        self.projection = ort.InferenceSession(str(projection), options, providers=cpu) if projection.exists() else None
        self.policy = self.manifest.get("time_policy", "frame-step")
        self.size = self.manifest["input"]["width"]
        self.patch = int(self.manifest["architecture"]["patch"])

    def gaussians(self, frames_u8: np.ndarray, context_times: list[float], targets: list[float], frame_step: float) -> np.ndarray:
        """Canonical Gaussians [B, N, 14] at `targets` from context frames [T, H, W, 3] (uint8)."""
        frames = frames_u8.astype(np.float32).transpose(0, 3, 1, 2) / 255.0 * 2 - 1
        (features,) = self.encoder.run(None, {"frames": frames})
        ctx, tgt = normalise_batch(context_times, targets, self.policy, frame_step)
        feeds = {"features": features, "context_times": ctx.astype(np.float32), "target_times": tgt.astype(np.float32)}
        if self.projection is not None:
            (feeds["context_projection"],) = self.projection.run(None, {"features": features})
        (gaussians,) = self.decoder.run(None, feeds)
        return gaussians


def world_clip(world: str, index: int, frames: int, size: int):
    """(frames [F, H, W, 3] in [0, 1], depth [F, H, W], world-to-camera [F, 4, 4], a renderer of
    the same scene from given cameras at given times) for clip `index` of `world`."""
    times = np.arange(frames) / synthetic.FPS
    if world == "train-world":
        # The test split's scenes as `c4g.eval.held_out` renders them (their 1 s paths; a window past
        # 1 s carries the camera's path on at its pace).
        scene = synthetic.make_scene(synthetic.SPLITS["test"][index])
        clip = synthetic.render_clip(scene, times, size)
        again = lambda t, cams: synthetic.render_clip(scene, t, size, cameras=cams).frames  # noqa: E731
        return clip.frames, clip.depth, clip.world_to_camera, again
    scene = eval_world.make_scene(index)
    rgb, depth, w2c = eval_world.render(scene, times, size)
    again = lambda t, cams: eval_world.render(scene, t, size, cameras=cams)[0]  # noqa: E731
    return rgb, depth, w2c, again


def block_mean(image: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """[H, W, 3] with every `rows` x `cols` block replaced by its mean."""
    h, w, c = image.shape
    means = image.reshape(h // rows, rows, w // cols, cols, c).mean(axis=(1, 3), keepdims=True)
    return np.broadcast_to(means, (h // rows, rows, w // cols, cols, c)).reshape(h, w, c)


def score_clip(package: Package, world: str, index: int, stride: int) -> dict:
    size = package.size
    context = np.arange(4) * stride
    targets = context[:-1] + stride // 2
    frames_f, depth, w2c_world, again = world_clip(world, index, int(context[-1]) + 1, size)
    times = np.arange(len(frames_f)) / synthetic.FPS
    frames_u8 = quantise(frames_f)
    frames = frames_u8.astype(np.float32) / 255.0
    first = depth[0]
    w2c, scale = synthetic.normalise_to_first_camera(w2c_world, int(context[0]), int(context[-1]), float(np.median(first[first > 0])))
    novel_model = np.stack([novel_pose(w2c[i]) for i in targets])
    novel_truth = quantise(again(times[targets], novel_world_poses(novel_model, w2c_world[0], scale))).astype(np.float32) / 255.0

    views = np.concatenate((targets, context))
    gaussians = package.gaussians(frames_u8[context], times[context].tolist(), times[views].tolist(), 1.0 / synthetic.FPS)
    with torch.no_grad():
        rendered = render_gaussians(torch.from_numpy(gaussians), w2c[views], size)
        unfitted_novel = render_gaussians(torch.from_numpy(gaussians[: len(targets)]), novel_model, size)
        # The first context camera is the model's frame at any scale: the others carry the fit.
        factor = fit_camera_scale(gaussians[len(targets) + 1 :], w2c[context[1:]], frames[context[1:]], size)
        fitted = gaussians[: len(targets)].copy()
        fitted[..., 0:6] /= factor
        interp = render_gaussians(torch.from_numpy(fitted), w2c[targets], size)
        novel = render_gaussians(torch.from_numpy(fitted), novel_model, size)
        # Scaling every position and size about the first camera's centre leaves its image as it
        # is and scales the parallax every other camera sees.
        ratio = float(np.median(gaussians[: len(targets), :, 2]) / np.median(depth[0][depth[0] > 0] * scale))
        rescaled = gaussians[: len(targets)].copy()
        rescaled[..., 0:6] /= ratio
        at_true_scale = render_gaussians(torch.from_numpy(rescaled), w2c[targets], size)
    unfitted, reconstructed = rendered[: len(targets)], rendered[len(targets) :]
    mean_colour = np.broadcast_to(frames[context].mean(axis=(0, 1, 2)), frames[0].shape)
    before = [frames[t - stride // 2] for t in targets]
    blend = [(frames[t - stride // 2] + frames[t + stride // 2]) / 2 for t in targets]
    rows, cols = package.patch // QUERY_GRID[0], package.patch // QUERY_GRID[1]
    in_blocks = lambda images, r, c: [block_mean(i, r, c) for i in images]  # noqa: E731
    methods = {
        "model": (interp, novel),
        "model, unfitted": (unfitted, unfitted_novel),
        "mean colour": ([mean_colour] * len(targets),) * 2,
        "nearest context frame": (before,) * 2,
        "blend of neighbours": (blend,) * 2,
        "true frame in query blocks": (in_blocks(frames[targets], rows, cols), in_blocks(novel_truth, rows, cols)),
        "true frame in patches": (in_blocks(frames[targets], package.patch, package.patch), in_blocks(novel_truth, package.patch, package.patch)),
    }
    scores = {
        name: {
            "interpolated": float(np.mean([psnr(a[k], frames[t]) for k, t in enumerate(targets)])),
            "novel": float(np.mean([psnr(b[k], novel_truth[k]) for k in range(len(targets))])),
        }
        for name, (a, b) in methods.items()
    }
    scores["model, reconstructed"] = {"interpolated": float(np.mean([psnr(r, frames[c]) for r, c in zip(reconstructed, context)])), "novel": None}
    scores["model at the true depth scale"] = {"interpolated": float(np.mean([psnr(a, frames[t]) for a, t in zip(at_true_scale, targets)])), "novel": None}
    scores["depth ratio"] = ratio
    scores["depth ratio, fitted"] = ratio / factor
    return scores


def protocol_arguments(ap: argparse.ArgumentParser, argv: list[str] | None) -> argparse.Namespace:
    """The protocol's command line (package, clips, strides, worlds, out), parsed and checked."""
    ap.add_argument("--package", type=Path, required=True)
    ap.add_argument("--clips", type=int, default=24, help="clips per world")
    ap.add_argument("--strides", type=int, nargs="+", default=[2, 4], help="source frames between context frames (even)")
    ap.add_argument("--worlds", nargs="+", default=list(WORLDS), choices=WORLDS)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    if any(s % 2 or s < 2 for s in args.strides):
        ap.error("strides must be even and at least 2 (targets lie half-way between context frames)")
    return args


def print_table(package: Package, args: argparse.Namespace, measure: str, results: dict, methods: tuple, digits: int) -> None:
    """The results as a Markdown table, a row per (world, stride) and view."""
    name = package.manifest.get("name", args.package.name)
    print(f"{name} ({args.package}), {args.clips} clips per world, 64 x 64, 10 fps, 4 context frames; {measure}\n")
    print("| world, stride | view | " + " | ".join(methods) + " |")
    print("|---|---|" + "---|" * len(methods))
    for key, scores in results.items():
        for view in ("interpolated", "novel"):
            print(f"| {key} | {view} | " + " | ".join("—" if scores[m][view] is None else f"{scores[m][view]:.{digits}f}" for m in methods) + " |")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.eval.generalisation", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    args = protocol_arguments(ap, argv)
    package = Package(args.package)
    results: dict = {}
    for world in args.worlds:
        for stride in args.strides:
            clips = [score_clip(package, world, i, stride) for i in range(args.clips)]
            results[f"{world}, stride {stride}"] = {
                name: {view: None if clips[0][name][view] is None else float(np.mean([c[name][view] for c in clips])) for view in ("interpolated", "novel")}
                for name in (*METHODS, *CEILINGS)
            }
            for name in RATIOS:
                ratios = np.log([c[name] for c in clips])
                results[f"{world}, stride {stride}"][name] = {"geometric mean": float(np.exp(ratios.mean())), "min": float(np.exp(ratios.min())), "max": float(np.exp(ratios.max()))}
            print(f"{world}, stride {stride}: done", file=sys.stderr, flush=True)
    print_table(package, args, "mean PSNR (dB)", results, METHODS, 2)
    print("\nCeilings (oracles that see the true frame) and the model's render of its own context frames (at their cameras):\n")
    print_table(package, args, "mean PSNR (dB)", results, CEILINGS, 2)
    print("\nDepth ratio (the model's median depth over the truth's, first frame; geometric mean [min, max]), as predicted and after the camera scale fit:\n")
    for key, scores in results.items():
        print(f"- {key}: " + "; ".join(f"{scores[n]['geometric mean']:.2f} [{scores[n]['min']:.2f}, {scores[n]['max']:.2f}]" for n in RATIOS))
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "generalisation.json").write_text(json.dumps({"package": str(args.package), "clips": args.clips, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
