"""Lifted object ids, scored: segmentation IoU at interpolated times and novel views, on two worlds.

    python -m c4g.eval.segmentation --package ../c4g-tiny-objects --clips 24 [--strides 2 4] [--out DIR]

The package's feature decoder lifts object ids (`feature_decoder.kind` "object-id", `c4g.train.lifting`):
it takes each context frame's per-patch object-id fractions and gives every Gaussian an 8-wide
feature, which composited at a camera and taken by its largest channel is an object-id mask. This
runs it as the service runs a package (its ONNX graphs on ONNX Runtime's CPU provider, its declared
time policy) on the clips of `c4g.eval.generalisation` (the same worlds, seeds, strides, context frames,
targets and novel cameras, the cameras fitted to the model's depth scale as the service fits given
cameras: `c4g.eval.generalisation.fit_camera_scale`), and scores each target's mask against the true one
(`render_object_ids` of the world's generator at that time and camera): IoU per object (the stage, id 0, is left out:
it is everything else), averaged over the objects in either mask, then over targets and clips.
The 2D baseline beside it: the nearest context frame's true mask (the earlier of two equidistant
ones), held as it is at novel views, as the colour baselines are.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch
import torch.nn.functional as F

from c4g.model.time_policy import normalise_batch
from c4g.raster.dense import render
from c4g.train import synthetic
from c4g.train.loop import INTRINSICS_NORMALISED, split_canonical

from . import world as eval_world
from .generalisation import Package, fit_camera_scale, print_table, protocol_arguments, world_clip
from .held_out import novel_pose, novel_world_poses, quantise

METHODS = ("model", "nearest context frame")


class ObjectPackage(Package):
    """A package whose feature decoder lifts object ids."""

    def __init__(self, path: Path):
        super().__init__(path)
        kind = self.manifest.get("feature_decoder", {}).get("kind")
        if kind != "object-id":
            raise ValueError(f"{path} lifts {kind or 'no'} features; this scores a package whose feature decoder lifts object ids (kind \"object-id\")")
        self.width = self.manifest["feature_decoder"]["feature_width"]
        self.patch = self.manifest["patch_size"]
        options = ort.SessionOptions()
        self.features = ort.InferenceSession(str(path / self.manifest["files"]["feature_decoder"]), options, providers=["CPUExecutionProvider"])

    def lifted(self, frames_u8: np.ndarray, ids: np.ndarray, context_times: list[float], targets: list[float], frame_step: float) -> tuple[np.ndarray, np.ndarray]:
        """(canonical Gaussians [B, N, 14], their features [B, N, K]) at `targets`, from context
        frames [T, H, W, 3] (uint8) and their object ids [T, H, W]."""
        frames = frames_u8.astype(np.float32).transpose(0, 3, 1, 2) / 255.0 * 2 - 1
        (features,) = self.encoder.run(None, {"frames": frames})
        one_hot = F.one_hot(torch.from_numpy(ids.astype(np.int64)), self.width).float().permute(0, 3, 1, 2)
        maps = F.avg_pool2d(one_hot, self.patch).flatten(2).transpose(1, 2).numpy()  # [T, P, K]
        ctx, tgt = normalise_batch(context_times, targets, self.policy, frame_step)
        feeds = {"features": features, "context_times": ctx.astype(np.float32), "target_times": tgt.astype(np.float32), "context_feature_maps": maps}
        names = {i.name for i in self.features.get_inputs()}
        gaussians, lifted = self.features.run(None, {k: v for k, v in feeds.items() if k in names})
        return gaussians, lifted


def world_ids(world: str, index: int, times: np.ndarray, size: int, cameras: np.ndarray | None = None) -> np.ndarray:
    """True object ids [T, H, W] of clip `index` of `world` at `times` (its own cameras, or `cameras`
    in its world frame)."""
    if world == "train-world":
        return synthetic.render_object_ids(synthetic.make_scene(synthetic.SPLITS["test"][index]), times, size, cameras)
    return eval_world.render_object_ids(eval_world.make_scene(index), times, size, cameras)


def masks(gaussians: np.ndarray, lifted: np.ndarray, w2c: np.ndarray, size: int) -> np.ndarray:
    """Object-id masks [B, H, W]: each set's features composited at its camera, largest channel."""
    f = INTRINSICS_NORMALISED * size
    out = []
    with torch.no_grad():
        for b in range(len(gaussians)):
            means, scales, rotations, opacities, colours = split_canonical(torch.from_numpy(gaussians[b]))
            image = render(means, scales, rotations, opacities, colours, (f, f, size / 2, size / 2), torch.from_numpy(w2c[b]).float(), size, size, features=torch.from_numpy(lifted[b]))
            out.append(image["features"].argmax(dim=-1).numpy())
    return np.stack(out)


def iou(predicted: np.ndarray, truth: np.ndarray) -> float | None:
    """Mean IoU over the objects (ids >= 1) in either mask; None when neither has one."""
    objects = sorted((set(np.unique(predicted)) | set(np.unique(truth))) - {0})
    scores = [np.logical_and(predicted == k, truth == k).sum() / np.logical_or(predicted == k, truth == k).sum() for k in objects]
    return float(np.mean(scores)) if scores else None


def score_clip(package: ObjectPackage, world: str, index: int, stride: int) -> dict[str, dict[str, list[float]]]:
    size = package.size
    context = np.arange(4) * stride
    targets = context[:-1] + stride // 2
    frames_f, depth, w2c_world, _ = world_clip(world, index, int(context[-1]) + 1, size)
    times = np.arange(len(frames_f)) / synthetic.FPS
    ids = world_ids(world, index, times, size)
    first = depth[0]
    w2c, scale = synthetic.normalise_to_first_camera(w2c_world, int(context[0]), int(context[-1]), float(np.median(first[first > 0])))
    novel_model = np.stack([novel_pose(w2c[i]) for i in targets])
    novel_truth = world_ids(world, index, times[targets], size, novel_world_poses(novel_model, w2c_world[0], scale))
    frames_u8 = quantise(frames_f)
    gaussians, lifted = package.lifted(frames_u8[context], ids[context], times[context].tolist(), times[targets].tolist(), 1.0 / synthetic.FPS)
    # The true cameras are given cameras: fitted to the model's depth scale as the service fits them.
    later = package.gaussians(frames_u8[context], times[context].tolist(), times[context[1:]].tolist(), 1.0 / synthetic.FPS)
    factor = fit_camera_scale(later, w2c[context[1:]], frames_u8[context[1:]].astype(np.float32) / 255.0, size)
    gaussians = gaussians.copy()
    gaussians[..., 0:6] /= factor
    interp, novel = masks(gaussians, lifted, w2c[targets], size), masks(gaussians, lifted, novel_model, size)
    nearest = [ids[t - stride // 2] for t in targets]
    scores: dict[str, dict[str, list[float]]] = {m: {"interpolated": [], "novel": []} for m in METHODS}
    for k, t in enumerate(targets):
        for method, (a, b) in {"model": (interp[k], novel[k]), "nearest context frame": (nearest[k], nearest[k])}.items():
            for view, predicted, truth in (("interpolated", a, ids[t]), ("novel", b, novel_truth[k])):
                value = iou(predicted, truth)
                if value is not None:
                    scores[method][view].append(value)
    return scores


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.eval.segmentation", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    args = protocol_arguments(ap, argv)
    try:
        package = ObjectPackage(args.package)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    results: dict = {}
    for world in args.worlds:
        for stride in args.strides:
            pooled = {m: {"interpolated": [], "novel": []} for m in METHODS}
            for i in range(args.clips):
                for m, views in score_clip(package, world, i, stride).items():
                    for view, values in views.items():
                        pooled[m][view].extend(values)
            results[f"{world}, stride {stride}"] = {m: {v: float(np.mean(x)) if x else None for v, x in views.items()} for m, views in pooled.items()}
            print(f"{world}, stride {stride}: done", file=sys.stderr, flush=True)
    print_table(package, args, "mean object IoU", results, METHODS, 3)
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "segmentation.json").write_text(json.dumps({"package": str(args.package), "clips": args.clips, "results": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
