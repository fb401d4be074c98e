"""Parity of a package whose LoRA was merged at export (`python -m c4g.wan.export ... --lora FILE
[--fp16]`) against the float32 PyTorch transformer with the same LoRA merged in float32: one
transformer call on random inputs at the package's size, through ONNX Runtime (CPU) and through
diffusers' module.

    python -m c4g.wan.check_merged --package DIR --lora FILE

The reference is rebuilt from `refiner.json`'s `source` (random-init: config and seed; checkpoint:
the diffusers folder). It runs first and is freed before ONNX Runtime loads the package, so that the
1.3B size fits in 24 GB. Prints the largest absolute difference, the RMS difference relative to the
reference's RMS, and the verdict against `--atol` (default 2e-2: what the f16 tiny fixture is held to,
measured ~2e-3 there; an f32 package is within ~1e-5).
"""

from __future__ import annotations

import argparse
import gc
import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from . import lora as lora_mod
from .configs import PRESETS, build_transformer
from .onnx_graphs import TransformerGraph


def reference_transformer(meta: dict):
    source = meta["source"]
    if source["kind"] == "random-init":
        return build_transformer(PRESETS[source["config"]].transformer, source["seed"])
    from diffusers import WanVACETransformer3DModel

    return WanVACETransformer3DModel.from_pretrained(source["path"], subfolder="transformer", torch_dtype=torch.float32).eval()


def inputs(meta: dict, seed: int = 7) -> dict[str, np.ndarray]:
    lat = meta["latent"]
    grid = (1, 16, lat["frames"], lat["height"], lat["width"])
    gen = torch.Generator().manual_seed(seed)
    return {
        "latents": torch.randn(*grid, generator=gen).numpy(),
        "timestep": np.array([625.0], np.float32),
        "text_embeddings": torch.randn(1, meta["text"]["tokens"], meta["text"]["dim"], generator=gen).numpy(),
        "control": torch.randn(1, 96, *grid[2:], generator=gen).numpy(),
        "control_scale": np.ones(len(meta["vace_layers"]), np.float32),
        "positions": np.arange(lat["frames"], dtype=np.int64),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--package", required=True, type=Path)
    parser.add_argument("--lora", required=True, type=Path, help="the LoRA the package was exported with")
    parser.add_argument("--atol", type=float, default=2e-2)
    args = parser.parse_args(argv)
    meta = json.loads((args.package / "refiner.json").read_text())
    merged = meta.get("lora_merged")
    if merged is None:
        parser.error(f"{args.package} has no LoRA merged at export (no `lora_merged` in refiner.json)")
    lora_file = args.lora / "adapter_model.safetensors" if args.lora.is_dir() else args.lora
    if hashlib.sha256(lora_file.read_bytes()).hexdigest() != merged["sha256"]:
        parser.error(f"{lora_file} is not the LoRA the package was exported with (sha256 differs)")
    feeds = inputs(meta)
    transformer = reference_transformer(meta)
    lora_mod.merge_into_transformer(transformer, lora_file, merged["scale"])
    graph = TransformerGraph(transformer, positions=True).eval()
    with torch.no_grad():
        expected = graph(*(torch.from_numpy(feeds[k]) for k in ("latents", "timestep", "text_embeddings", "control", "control_scale", "positions"))).numpy()
    del graph, transformer
    gc.collect()
    options = ort.SessionOptions()
    options.log_severity_level = 3
    session = ort.InferenceSession(str(args.package / meta["files"]["transformer"]), options, providers=["CPUExecutionProvider"])
    names = {i.name for i in session.get_inputs()}
    got = session.run(None, {k: v for k, v in feeds.items() if k in names})[0]
    diff = np.abs(got.astype(np.float64) - expected)
    rel_rms = float(np.sqrt((diff**2).mean() / (expected.astype(np.float64) ** 2).mean()))
    ok = bool(diff.max() <= args.atol)
    print(json.dumps({"package": str(args.package), "precision": meta["precision"], "lora_modules": merged["modules"], "max_abs": float(diff.max()), "relative_rms": rel_rms, "atol": args.atol, "ok": ok}))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
