"""What a package does on real footage: pictures and numbers for a model card.

    python -m c4g.eval.real_footage --package ../c4g-tiny --video ../../../shared/data/dog/01_dog.mp4 \
        --start 2.0 --out ../c4g-tiny/real-dog.png [--compare ../c4g-tiny-v1]

Takes frames at 10 fps from `--start` seconds of the video (FFmpeg decodes; centre crop and
Lanczos resize as the service does), uses 4 context frames at stride 2 (c4g-tiny's training
spacing, 0.2 s apart) and decodes the 3 frames between them; renders each set at the first
context camera with C4G's intrinsics (these clips carry no cameras: the model's frame is the first
camera's, and a static camera stays there; a moving one does not, which the picture shows).
Writes a picture (rows: the true frames; each package's renders; the nearest context frame) and
prints PSNR against the true frames beside the nearest-frame baseline. Nothing here is ground
truth beyond the frames themselves, so novel views are not scored.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from c4g.model.preprocess import preprocess_u8
from c4g.raster.metrics import psnr

from .generalisation import Package
from .held_out import quantise, render_gaussians

FPS = 10
STRIDE = 2
CONTEXT = 4


def frames_of(video: Path, start: float, count: int, size: int) -> np.ndarray:
    """`count` frames [count, size, size, 3] (uint8) at FPS from `start` s, preprocessed."""
    with tempfile.TemporaryDirectory() as tmp:
        cmd = ["ffmpeg", "-v", "error", "-ss", str(start), "-i", str(video), "-vf", f"fps={FPS}", "-frames:v", str(count), f"{tmp}/%03d.png"]
        subprocess.run(cmd, check=True)
        files = sorted(Path(tmp).glob("*.png"))
        if len(files) < count:
            raise ValueError(f"{video}: {len(files)} frames from {start} s at {FPS} fps, {count} needed")
        return np.stack([preprocess_u8(Image.open(f), size) for f in files])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.eval.real_footage", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--package", type=Path, required=True)
    ap.add_argument("--compare", type=Path, nargs="*", default=[], help="other packages shown beside it")
    ap.add_argument("--video", type=Path, required=True)
    ap.add_argument("--start", type=float, default=0.0)
    ap.add_argument("--out", type=Path, required=True, help="the picture (PNG)")
    args = ap.parse_args(argv)
    packages = [Package(p) for p in [args.package, *args.compare]]
    size = packages[0].size
    span = (CONTEXT - 1) * STRIDE + 1
    frames = frames_of(args.video, args.start, span, size)
    times = np.arange(span) / FPS
    context = np.arange(CONTEXT) * STRIDE
    targets = context[:-1] + STRIDE // 2
    truth = frames.astype(np.float32) / 255.0
    rows = [np.concatenate([truth[t] for t in targets], axis=1)]
    for path, package in zip([args.package, *args.compare], packages):
        g = package.gaussians(frames[context], times[context].tolist(), times[targets].tolist(), 1.0 / FPS)
        with torch.no_grad():
            renders = render_gaussians(torch.from_numpy(g), np.stack([np.eye(4)] * len(targets)), size)
        scores = [psnr(quantise(renders[k]).astype(np.float32) / 255.0, truth[t]) for k, t in enumerate(targets)]
        print(f"{package.manifest.get('name', path.name)} {package.manifest.get('version', '')}: {np.mean(scores):.2f} dB at the interpolated frames")
        rows.append(np.concatenate(list(renders), axis=1))
    nearest = [truth[t - STRIDE // 2] for t in targets]
    print(f"nearest context frame: {np.mean([psnr(n, truth[t]) for n, t in zip(nearest, targets)]):.2f} dB")
    rows.append(np.concatenate(nearest, axis=1))
    gap = np.ones((2, rows[0].shape[1], 3))
    sheet = quantise(np.concatenate([r for row in rows for r in (row, gap)][:-1], axis=0))
    img = Image.fromarray(sheet)
    img.resize((img.width * 3, img.height * 3), Image.NEAREST).save(args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
