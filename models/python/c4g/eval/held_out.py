"""Measure a trained small C4G on the held-out test split, against simple baselines, and write the
test clips the service's end-to-end tests use.

    python -m c4g.eval.held_out --checkpoint runs/c4g-tiny/c4g-tiny.ckpt --config runs/c4g-tiny/config.json \\
        --clips 64 --out ../c4g-tiny

Protocol, per test clip (the scene of seed SPLITS["test"][i]): T context frames at stride 2 from
frame 0 (frames 0, 2, ..., 2T - 2), targets at the odd frames between them.
- Interpolated timestamps: the model's render at each target's ground-truth camera, against
  the ground-truth frame.
- Novel views: the same target times from a camera moved off the clip's path (NOVEL_OFFSET in the
  model's units, and a turn of NOVEL_YAW), against the scene rendered from that camera.
- Baselines (they cannot move the camera, so at novel views they are held against the novel frame as
  they are): the mean colour of the context frames; the nearest context frame in time; the average
  of the two context frames on either side.
All inputs and ground truths are quantised to 8 bits first, as the service sees them. PSNR and SSIM
are `c4g.raster.metrics` (the renderer crate's metrics are held against it).

Writes evaluation.json, contact-sheet.png and test-clips/ into --out.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from c4g.model.checkpoint import load_checkpoint
from c4g.model.config import C4GConfig
from c4g.model.network import C4G
from c4g.model.time_policy import normalise_batch
from c4g.raster.fast import render_batch
from c4g.raster.metrics import psnr, ssim
from c4g.train.dataset import SIZE
from c4g.train.loop import INTRINSICS_NORMALISED, split_canonical
from c4g.train.synthetic import FPS, FRAMES, SPLITS, _axis_angle, make_scene, normalise_to_first_camera, render_clip

NOVEL_OFFSET = np.array([0.15, -0.05, 0.1])
NOVEL_YAW = math.radians(6.0)
TEST_CLIPS = 3  # committed for the service's tests


def quantise(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0, 1) * 255).astype(np.uint8)


def novel_pose(w2c_model: np.ndarray) -> np.ndarray:
    """The camera moved by NOVEL_OFFSET (its own axes, model units) and turned by NOVEL_YAW."""
    delta = np.eye(4)
    delta[:3, :3] = _axis_angle(np.array([0.0, 1.0, 0.0]), NOVEL_YAW)
    delta[:3, 3] = -delta[:3, :3] @ NOVEL_OFFSET
    return delta @ w2c_model


def render_gaussians(gaussians: torch.Tensor, poses: np.ndarray, size: int) -> np.ndarray:
    """Canonical Gaussians [B, N, 14] at poses [B, 4, 4] → rgb [B, H, W, 3] in [0, 1]."""
    f = INTRINSICS_NORMALISED * size
    out = render_batch(*split_canonical(gaussians.double()), (f, f, size / 2, size / 2), torch.from_numpy(poses), size, size)
    return out["rgb"].clamp(0, 1).numpy()


def novel_world_poses(novel_model: np.ndarray, first_world: np.ndarray, scale: float) -> np.ndarray:
    """Novel cameras [V, 4, 4] given in the model's frame, back in the scene's world: the frame
    of the first context camera `first_world` (world-to-camera), scaled by `scale` model units
    per world unit (`normalise_to_first_camera`)."""
    to_model = np.linalg.inv(first_world)
    out = []
    for p in novel_model:
        q = p.copy()
        q[:3, 3] /= scale  # model units → world units
        out.append(q @ np.linalg.inv(to_model))
    return np.stack(out)


@torch.no_grad()
def evaluate_clip(model: C4G, seed: int, context_frames: int) -> dict:
    scene = make_scene(seed)
    span = 2 * context_frames - 1
    times = np.arange(span) / FPS
    clip = render_clip(scene, times, SIZE)
    frames_u8 = quantise(clip.frames)
    frames = frames_u8.astype(np.float32) / 255.0
    first = clip.depth[0]
    w2c, scale = normalise_to_first_camera(clip.world_to_camera, 0, span - 1, float(np.median(first[first > 0])))
    ctx, tgt = np.arange(0, span, 2), np.arange(1, span, 2)
    # Novel views: GT rendered from the moved camera, expressed back in the world.
    novel_model = np.stack([novel_pose(w2c[i]) for i in tgt])
    novel_world = novel_world_poses(novel_model, clip.world_to_camera[0], scale)
    novel_gt = quantise(render_clip(scene, times[tgt], SIZE, cameras=novel_world).frames).astype(np.float32) / 255.0

    features = model.encode(torch.from_numpy(frames[ctx]).permute(0, 3, 1, 2) * 2 - 1)
    c, t = normalise_batch(times[ctx].tolist(), times[tgt].tolist())
    gaussians = model.decode_canonical(features, torch.from_numpy(c), torch.from_numpy(t))
    interp = render_gaussians(gaussians, w2c[tgt], SIZE)
    novel = render_gaussians(gaussians, novel_model, SIZE)

    mean_colour = np.broadcast_to(frames[ctx].mean(axis=(0, 1, 2)), frames[0].shape)
    methods = {
        "c4g-tiny": (interp, novel),
        "mean colour": ([mean_colour] * len(tgt),) * 2,
        "nearest context frame": ([frames[i - 1] for i in tgt],) * 2,  # equidistant: the earlier one
        "blend of neighbours": ([(frames[i - 1] + frames[i + 1]) / 2 for i in tgt],) * 2,
    }
    scores = {}
    for name, (at_targets, at_novel) in methods.items():
        scores[name] = {
            "interpolated": {
                "psnr": [psnr(at_targets[k], frames[i]) for k, i in enumerate(tgt)],
                "ssim": [ssim(at_targets[k], frames[i]) for k, i in enumerate(tgt)],
            },
            "novel": {
                "psnr": [psnr(at_novel[k], novel_gt[k]) for k in range(len(tgt))],
                "ssim": [ssim(at_novel[k], novel_gt[k]) for k in range(len(tgt))],
            },
        }
    return {
        "seed": seed,
        "scores": scores,
        "clip": clip,
        "frames_u8": frames_u8,
        "model_w2c": w2c,
        "scale": scale,
        "interp": interp,
        "novel": novel,
        "novel_gt": novel_gt,
        "novel_model": novel_model,
    }


_WORKER_MODEL: C4G | None = None


def _load_worker(checkpoint: Path, config: dict) -> None:
    global _WORKER_MODEL
    torch.set_num_threads(1)
    _WORKER_MODEL = load_checkpoint(checkpoint, C4GConfig.from_dict(config)).eval()


def _evaluate_in_worker(job: tuple[int, int]) -> dict:
    assert _WORKER_MODEL is not None
    return evaluate_clip(_WORKER_MODEL, *job)


def summarise(results: list[dict]) -> dict:
    out = {}
    for name in results[0]["scores"]:
        out[name] = {}
        for kind in ("interpolated", "novel"):
            out[name][kind] = {
                m: round(float(np.mean([v for r in results for v in r["scores"][name][kind][m]])), 4) for m in ("psnr", "ssim")
            }
    return out


def contact_sheet(results: list[dict], path: Path, scale: int = 3) -> None:
    """Per clip, two rows: ground truth then c4g-tiny, at every target and its novel view."""
    rows = []
    for r in results:
        frames = r["frames_u8"].astype(np.float32) / 255.0
        tgt = np.arange(1, len(frames), 2)
        gt = np.concatenate([frames[i] for i in tgt] + list(r["novel_gt"]), axis=1)
        pred = np.concatenate(list(r["interp"]) + list(r["novel"]), axis=1)
        rows += [gt, pred, np.ones((4, gt.shape[1], 3))]
    sheet = quantise(np.concatenate(rows[:-1], axis=0))
    img = Image.fromarray(sheet)
    img.resize((img.width * scale, img.height * scale), Image.NEAREST).save(path)


def write_test_clip(r: dict, folder: Path) -> None:
    """Frames as PNGs plus everything known about them (times, cameras, ground truth), and the
    Python path's scores for the engine parity test."""
    folder.mkdir(parents=True, exist_ok=True)
    clip = r["clip"]
    for i, f in enumerate(r["frames_u8"]):
        Image.fromarray(f).save(folder / f"frame-{i:02d}.png")
    span = len(r["frames_u8"])
    meta = {
        "seed": r["seed"],
        "fps": FPS,
        "times": clip.times.tolist(),
        "frames": [f"frame-{i:02d}.png" for i in range(span)],
        "context": list(range(0, span, 2)),
        "targets": list(range(1, span, 2)),
        "intrinsics_normalised": [INTRINSICS_NORMALISED, INTRINSICS_NORMALISED, 0.5, 0.5],
        "world_to_camera_model": r["model_w2c"].tolist(),
        "novel_world_to_camera_model": r["novel_model"].tolist(),
        "scale_model_per_world": r["scale"],
        "python_psnr": {
            "interpolated": r["scores"]["c4g-tiny"]["interpolated"]["psnr"],
            "novel": r["scores"]["c4g-tiny"]["novel"]["psnr"],
        },
    }
    (folder / "clip.json").write_text(json.dumps(meta, indent=1) + "\n")
    for k, f in enumerate(r["novel_gt"]):
        Image.fromarray(quantise(f)).save(folder / f"novel-{k:02d}.png")
    np.savez_compressed(
        folder / "ground-truth.npz",
        depth=clip.depth.astype(np.float16),
        dynamic_mask=clip.dynamic_mask,
        world_to_camera_world=clip.world_to_camera,
        tracks_2d=clip.tracks_2d.astype(np.float32),
        tracks_3d_world=clip.tracks_3d.astype(np.float32),
        tracks_visible=clip.tracks_visible,
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.eval.held_out", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--checkpoint", type=Path, required=True)
    ap.add_argument("--config", type=Path, required=True)
    ap.add_argument("--clips", type=int, default=64)
    ap.add_argument("--context-frames", type=int, nargs="+", default=[4, 6])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--processes", type=int, default=2)
    args = ap.parse_args(argv)
    config = json.loads(args.config.read_text())
    seeds = list(SPLITS["test"][: args.clips])
    report = {"clips": len(seeds), "test_seeds": [seeds[0], seeds[-1]], "size": SIZE, "by_context_frames": {}}
    for t in args.context_frames:
        if 2 * t - 1 > FRAMES:
            raise SystemExit(f"--context-frames {t} needs {2 * t - 1} frames; clips have {FRAMES}")
        # Spawned workers, one model each: clips are independent, and a fork would inherit thread pools.
        with get_context("spawn").Pool(args.processes, initializer=_load_worker, initargs=(args.checkpoint, config)) as pool:
            results = pool.map(_evaluate_in_worker, [(s, t) for s in seeds])
        report["by_context_frames"][str(t)] = summarise(results)
        if t == args.context_frames[0]:
            args.out.mkdir(parents=True, exist_ok=True)
            contact_sheet(results[:4], args.out / "contact-sheet.png")
            for r in results[:TEST_CLIPS]:
                write_test_clip(r, args.out / "test-clips" / f"seed-{r['seed']}")
        print(json.dumps({t: report["by_context_frames"][str(t)]}, indent=1), flush=True)
    (args.out / "evaluation.json").write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
