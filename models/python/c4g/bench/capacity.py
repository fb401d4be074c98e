"""What c4g-tiny's size costs: the candidates' inference and training time, measured in one run.

    python -m c4g.bench.capacity [--repeats 5] [--threads 2]

Issue #16 asks for capacity "where it pays" within a stated CPU budget. The budget we hold the
default model to, on our 2-core development machine: a decode of one target within about 50 ms and
the encoding of 4 context frames within 100 ms on ONNX Runtime (so a 64-frame video decodes in
about 2 s and an upload answers at once), and training steps that let `scripts/train-tiny` finish
from nothing in under 3 hours on the same machine (the model card, "Capacity"). For each candidate (c4g-tiny's
widths at several Gaussian counts, input sizes and decoder widths; random weights: the cost does
not depend on the values) this exports the encoder and decoder as the export tool does and times
them on ONNX Runtime's CPU provider, then times one training window's forward and backward in
PyTorch (encode 4 frames, decode 4 targets, render them with the fast rasterizer at 64-pixel
renders scaled by the input size). Calls alternate between candidates so that a noisy machine
slows all alike; medians of `--repeats`. Prints a Markdown table; the ratios within one run are
what to read.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from c4g.model.config import C4GConfig
from c4g.model.decoder import to_canonical
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.package.export import export_package
from c4g.raster.fast import render_batch
from c4g.train.loop import TINY, split_canonical
from c4g.train.synthetic import C4G_FOCAL

# (label, changes to c4g-tiny's configuration)
CANDIDATES = (
    ("c4g-tiny (512 Gaussians, 64 px, width 128)", {}),
    ("1024 Gaussians", {"queries": 1024}),
    ("2048 Gaussians (the paper's count)", {"queries": 2048}),
    ("96 px input", {"image_size": 96, "pos_embed_grid": 12, "queries": 1152}),
    ("twice the widths (encoder 128, decoder 256)", {"dino_dim": 128, "aggregator_dim": 128, "decoder_dim": 256, "decoder_heads": 8, "decoder_mlp": 1024}),
)


def _sessions(model: C4G, tmp: Path, threads: int) -> tuple[ort.InferenceSession, ort.InferenceSession]:
    export_package(model, tmp, "capacity", "0", {"kind": "random"}, decoder_form="plain")
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    load = lambda name: ort.InferenceSession(str(tmp / name), options, providers=["CPUExecutionProvider"])  # noqa: E731
    return load("encoder.onnx"), load("decoder.onnx")


def _training_window(model: C4G) -> None:
    cfg = model.cfg
    frames = torch.rand(4, 3, cfg.image_size, cfg.image_size) * 2 - 1
    features = model.encode(frames)
    ctx = torch.tensor([[-1.0, -1 / 3, 1 / 3, 1.0]]).expand(4, -1)
    tgt = torch.tensor([-2 / 3, 0.0, 0.5, 2 / 3])
    g = split_canonical(to_canonical(model.decode(features, ctx, tgt)))
    size = cfg.image_size
    f = C4G_FOCAL * size
    poses = torch.eye(4).expand(4, 4, 4).clone()
    out = render_batch(*g, (f, f, size / 2, size / 2), poses, size, size)
    out["rgb"].mean().backward()


def measure(repeats: int, threads: int) -> list[dict]:
    torch.set_num_threads(threads)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (label, change) in enumerate(CANDIDATES):
            cfg = C4GConfig.from_dict({**TINY.to_dict(), **change})
            model = C4G(cfg)
            random_init(model, seed=0)
            folder = Path(tmp) / str(i)
            encoder, decoder = _sessions(model.eval(), folder, threads)
            frames = np.random.default_rng(0).uniform(-1, 1, (4, 3, cfg.image_size, cfg.image_size)).astype(np.float32)
            rows.append({"label": label, "cfg": cfg, "model": model.train(), "encoder": encoder, "decoder": decoder, "frames": frames,
                         "encode": [], "decode": [], "train": [], "params": sum(p.numel() for p in model.parameters())})
        for row in rows:  # one untimed call each: first-call costs (allocation, prepacking) apart
            _time_once(row)
        for _ in range(repeats):
            for row in rows:
                for key, seconds in _time_once(row).items():
                    row[key].append(seconds)
    return rows


def _time_once(row: dict) -> dict[str, float]:
    t0 = time.perf_counter()
    features = row["encoder"].run(None, {"frames": row["frames"]})[0]
    t1 = time.perf_counter()
    row["decoder"].run(None, {"features": features, "context_times": np.array([[-1, -1 / 3, 1 / 3, 1]], np.float32), "target_times": np.array([0.0], np.float32)})
    t2 = time.perf_counter()
    row["model"].zero_grad()
    _training_window(row["model"])
    t3 = time.perf_counter()
    return {"encode": t1 - t0, "decode": t2 - t1, "train": t3 - t2}


def table(rows: list[dict]) -> str:
    base = statistics.median(rows[0]["train"])
    lines = [
        "| candidate | parameters | encode T = 4 (ms) | decode B = 1 (ms) | training window (s) | training vs c4g-tiny |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        train = statistics.median(r["train"])
        lines.append(
            f"| {r['label']} | {r['params'] / 1e6:.2f} M | {1e3 * statistics.median(r['encode']):.1f} | "
            f"{1e3 * statistics.median(r['decode']):.2f} | {train:.2f} | {train / base:.2f}x |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.bench.capacity", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    print(table(measure(args.repeats, args.threads)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
