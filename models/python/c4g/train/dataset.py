"""Rendered splits of the procedural scenes, and the training samples cut from them.

    python -m c4g.train.dataset --split train --count 2400 --out data/synthetic
    python -m c4g.train.dataset --split validation --count 64 --out data/synthetic
    python -m c4g.train.dataset --world 2 --frames 17 --split train --count 2400 --out data/world2

Each split is one `<split>.npz`: for C clips of F frames (`--frames`, default `synthetic.FRAMES`:
clips of (F - 1) / FPS seconds) at `SIZE`,
frames uint8 [C, F, H, W, 3], expected depth float16 [C, F, H, W] (world units), dynamic masks
bool [C, F, H, W], world-to-camera poses float64 [C, F, 4, 4], media times float64 [C, F] and the
scene seeds [C] and the world [] (`synthetic.make_scene`'s `world`: 1, c4g-tiny's, or 2, the wider
one). Clip i of a split is the scene of seed `SPLITS[split][i]`, so a split is a pure function of
its world, name and count. With `--object-ids`, also object ids uint8 [C, F, H, W]
(`synthetic.render_object_ids`: 0 the room, k the k-th object), the target of object-identity
feature lifting (`c4g.train.loop --features object-id`); without, the split is as it always was.

A training sample is a window of (T - 1) s + 1 consecutive frames: every s-th one is context (stride
s = 2 as in the paper; larger strides put wider gaps in training), the frames between them targets. Cameras and depths are expressed in the
model's frame (`synthetic.normalise_to_first_camera`).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

import numpy as np

from .synthetic import FPS, FRAMES, SPLITS, make_scene, normalise_to_first_camera, render_clip, render_object_ids

SIZE = 64


def _one_thread() -> None:
    """A worker's libraries on one thread each: the pool runs a worker per core, and the Numba
    rasterizer's parallel loops would otherwise start a thread per core in every worker (on a
    16-core machine, 256 threads contending for 16 cores)."""
    import numba
    import torch

    torch.set_num_threads(1)
    numba.set_num_threads(1)


def _render(job: tuple[int, int, int, bool]) -> tuple:
    seed, world, frames, with_ids = job
    scene = make_scene(seed, duration=(frames - 1) / FPS, world=world)
    times = np.arange(frames) / FPS
    clip = render_clip(scene, times, SIZE)
    ids = render_object_ids(scene, times, SIZE) if with_ids else None
    frames = np.round(clip.frames * 255).astype(np.uint8)
    return frames, clip.depth.astype(np.float16), clip.dynamic_mask, clip.world_to_camera, clip.times, ids


def generate(split: str, count: int, out: Path, processes: int = 2, world: int = 1, frames: int = FRAMES, object_ids: bool = False) -> Path:
    seeds = list(SPLITS[split][:count])
    jobs = [(s, world, frames, object_ids) for s in seeds]
    if processes > 1:
        # Spawned, not forked: a fork would inherit the parent's torch and Numba thread pools.
        with get_context("spawn").Pool(processes, initializer=_one_thread) as pool:
            rows = pool.map(_render, jobs, chunksize=8)
    else:
        rows = [_render(j) for j in jobs]
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{split}.npz"
    np.savez(
        path,
        frames=np.stack([r[0] for r in rows]),
        depth=np.stack([r[1] for r in rows]),
        dynamic=np.stack([r[2] for r in rows]),
        world_to_camera=np.stack([r[3] for r in rows]),
        times=np.stack([r[4] for r in rows]),
        seeds=np.asarray(seeds, dtype=np.int64),
        world=np.asarray(world),
        **({"object_ids": np.stack([r[5] for r in rows])} if object_ids else {}),
    )
    return path


@dataclass
class Split:
    frames: np.ndarray
    depth: np.ndarray
    dynamic: np.ndarray
    world_to_camera: np.ndarray
    times: np.ndarray
    seeds: np.ndarray
    object_ids: np.ndarray | None = None  # only in splits made with object ids

    @classmethod
    def load(cls, path: Path) -> "Split":
        with np.load(path) as z:
            keys = ("frames", "depth", "dynamic", "world_to_camera", "times", "seeds") + (("object_ids",) if "object_ids" in z else ())
            return cls(**{k: z[k] for k in keys})

    def __len__(self) -> int:
        return len(self.seeds)


@dataclass
class Sample:
    """One clip window in the model's frame. `context` and `targets` index into the window."""

    frames: np.ndarray  # [2T-1, H, W, 3] float32 in [0, 1]
    depth: np.ndarray  # [2T-1, H, W] model units
    dynamic: np.ndarray  # [2T-1, H, W] bool
    world_to_camera: np.ndarray  # [2T-1, 4, 4] model frame
    times: np.ndarray  # [2T-1] media seconds
    context: np.ndarray
    targets: np.ndarray
    scale: float  # model units per world unit
    object_ids: np.ndarray | None = None  # [2T-1, H, W] uint8, when the split has them


def span(context_frames: int, stride: int = 2) -> int:
    """Frames a window of `context_frames` context frames `stride` apart covers."""
    return (context_frames - 1) * stride + 1


def window(split: Split, clip: int, start: int, context_frames: int, stride: int = 2) -> Sample:
    idx = start + np.arange(span(context_frames, stride))
    depth = split.depth[clip, idx].astype(np.float32)
    first = depth[0]
    w2c, scale = normalise_to_first_camera(
        split.world_to_camera[clip, idx], 0, len(idx) - 1, float(np.median(first[first > 0])) if (first > 0).any() else 1.0
    )
    return Sample(
        split.frames[clip, idx].astype(np.float32) / 255.0,
        depth * scale,
        split.dynamic[clip, idx],
        w2c,
        split.times[clip, idx],
        np.arange(0, len(idx), stride),
        np.setdiff1d(np.arange(len(idx)), np.arange(0, len(idx), stride)),
        scale,
        split.object_ids[clip, idx] if split.object_ids is not None else None,
    )


def random_windows(split: Split, rng: np.random.Generator, batch: int, context_frames: int, stride: int = 2) -> list[Sample]:
    clips = rng.integers(0, len(split), batch)
    length = span(context_frames, stride)
    frames = split.frames.shape[1]
    if length > frames:
        raise ValueError(f"{context_frames} context frames {stride} apart span {length} frames; the clips have {frames}")
    return [window(split, int(c), int(rng.integers(0, frames - length + 1)), context_frames, stride) for c in clips]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.train.dataset", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--split", choices=list(SPLITS), required=True)
    ap.add_argument("--count", type=int, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--processes", type=int, default=2)
    ap.add_argument("--world", type=int, choices=[1, 2], default=1, help="1: c4g-tiny's world; 2: the wider one")
    ap.add_argument("--frames", type=int, default=FRAMES, help="frames a clip (at 10 fps)")
    ap.add_argument("--object-ids", action="store_true", help="also render each pixel's object id (for --features object-id training)")
    args = ap.parse_args(argv)
    path = generate(args.split, args.count, args.out, args.processes, args.world, args.frames, args.object_ids)
    print(f"wrote {path} ({args.count} clips)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
