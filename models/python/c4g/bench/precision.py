"""What a package's precision costs and saves: f32 against its f16 and int8 conversions.

    python -m c4g.bench.precision --package models/c4g-tiny

Converts the (f32) package with `c4g.package.precision` into a scratch folder, then times one encode of
the first test clip's context frames and one decode (B = 1, a target mid-span) through ONNX
Runtime with the engine's session settings, alternating precisions call by call (median of
`--repeats`), and prints each one's graph size and its largest position error against f32. The
table in docs/benchmarks.md ("Precision") is this command's output.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
from PIL import Image

from c4g.package.precision import convert_package

from .decoder import session_options


def context_frames(package: Path) -> np.ndarray:
    """The first test clip's context frames, as the encoder takes them (the clips are at its size)."""
    clip = sorted((package / "test-clips").iterdir())[0]
    meta = json.loads((clip / "clip.json").read_text())
    images = [Image.open(clip / meta["frames"][i]).convert("RGB") for i in meta["context"]]
    return np.stack([np.asarray(im, np.float32).transpose(2, 0, 1) / 127.5 - 1.0 for im in images])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.precision", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--package", type=Path, default=Path("models/c4g-tiny"), help="an f32 package with test-clips/")
    ap.add_argument("--repeats", type=int, default=30)
    args = ap.parse_args(argv)
    frames = context_frames(args.package)
    t = len(frames)
    context = (np.arange(t, dtype=np.float32) / max(t - 1, 1))[None]
    target = np.array([0.5], np.float32)
    with tempfile.TemporaryDirectory() as tmp:
        packages = {"f32": args.package}
        for precision in ("f16", "int8"):
            packages[precision] = Path(tmp) / precision
            convert_package(args.package, packages[precision], precision)
        sessions = {
            name: tuple(ort.InferenceSession(str(p / f"{g}.onnx"), session_options(), providers=["CPUExecutionProvider"]) for g in ("encoder", "decoder"))
            for name, p in packages.items()
        }
        times = {name: ([], []) for name in sessions}
        outputs = {}
        for _ in range(args.repeats):
            for name, (encoder, decoder) in sessions.items():
                start = time.perf_counter()
                (features,) = encoder.run(None, {"frames": frames})
                middle = time.perf_counter()
                (gaussians,) = decoder.run(None, {"features": features, "context_times": context, "target_times": target})
                times[name][0].append(middle - start)
                times[name][1].append(time.perf_counter() - middle)
                outputs[name] = gaussians
        print("| precision | encode | decode | graphs | largest position error |")
        print("|---|---|---|---|---|")
        for name, p in packages.items():
            size = sum(f.stat().st_size for f in p.iterdir() if f.suffix in (".onnx", ".data"))
            error = np.abs(outputs[name][..., 0:3] - outputs["f32"][..., 0:3]).max()
            encode, decode = (1000 * statistics.median(v) for v in times[name])
            print(f"| {name} | {encode:.1f} ms | {decode:.1f} ms | {size / 1e6:.1f} MB | {'—' if name == 'f32' else f'{error:.2g}'} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
