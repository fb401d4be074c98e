"""Builds the committed test fixtures.

`models/fixtures/c4g-small/`:
- the package: the reduced official reference checkpoint (`../shared/reference/c4g-official-small/`)
  exported with our export tool (plain decoder form), plus a feature-lifting decoder with seeded
  random weights (the official checkpoint has none);
- `reference.safetensors` + `reference.json`: inputs and outputs of the PyTorch mirror on real frames
  (the bedroom clip, preprocessed with Pillow), for T in {1, 4, 16}, targets at both ends of the span
  and between frames, under both time policies.

`models/fixtures/decoder-forms/` (`--decoder-forms`): one very small seeded random model (official
layout, every width shrunk) exported in both decoder forms, `plain/` and `precomputed/`, with the
PyTorch mirror's outputs on seeded frames, so that a test can hold both forms to each other and to
the mirror.

`models/fixtures/feature-stream/` (`--feature-stream`): a very small seeded random model with a
feature stream that lifts the encoder's own features (`feature_decoder.kind` "encoder": the context
feature maps are the encoding's features, F = C), with the mirror's Gaussians and per-Gaussian
features, for the engine's feature lifting to be held to.

    python -m c4g.package.fixture --shared ../shared --out models/fixtures/c4g-small
    python -m c4g.package.fixture --decoder-forms --out models/fixtures/decoder-forms
    python -m c4g.package.fixture --feature-stream --out models/fixtures/feature-stream
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from safetensors.numpy import save_file

from c4g.model.checkpoint import load_into, read_state_dict
from c4g.model.config import OFFICIAL_SMALL, C4GConfig
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.model.preprocess import preprocess_u8, to_model_input
from c4g.model.time_policy import normalise_batch

from .export import export_package

FEATURE_DIM = 32
FEATURE_SEED = 1
FRAME_STRIDE = 2  # as the reference's qualitative script: context frames at a temporal stride of 2

# (name, number of context frames, target timestamps in source frame indices, policy)
CASES = [
    ("T1", 1, [0.0], "stable"),
    ("T4", 4, [0.0, 1.0, 3.0, 6.0], "stable"),
    ("T4_reference", 4, [1.0, 3.0, 6.0], "reference"),
    ("T16", 16, [0.0, 1.0, 15.0, 29.5, 30.0], "stable"),
    ("T16_reference", 16, [1.0, 15.0, 30.0], "reference"),
]


def build(shared: Path, out: Path) -> None:
    ckpt = shared / "reference/c4g-official-small/c4g_official_small.ckpt"
    cfg = C4GConfig.from_dict({**OFFICIAL_SMALL.to_dict(), "feature_dim": FEATURE_DIM})
    model = C4G(cfg)
    random_init(model, seed=FEATURE_SEED)
    load_into(model, read_state_dict(ckpt))
    model.eval()
    provenance = {
        "kind": "checkpoint",
        "source": "shared/reference/c4g-official-small/c4g_official_small.ckpt (random weights, reduced sizes, official layout)",
        "feature_decoder": f"random init, seed {FEATURE_SEED} (the checkpoint has none)",
    }
    export_package(
        model, out, "c4g-small", "0.1.0", provenance, "Test fixture: the reduced official reference model.", decoder_form="plain"
    )

    n_frames = max(c[1] for c in CASES)
    paths = sorted((shared / "data/bedroom/frames").glob("*.jpg"))[: n_frames * FRAME_STRIDE : FRAME_STRIDE]
    frames_u8 = np.stack([preprocess_u8(Image.open(p), cfg.image_size) for p in paths])
    tensors = {"frames_u8": frames_u8}
    rng = np.random.default_rng(FEATURE_SEED)
    tensors["feature_maps"] = rng.standard_normal((n_frames, cfg.tokens_per_frame, FEATURE_DIM)).astype(np.float32)
    index = []
    with torch.no_grad():
        for name, t, targets, policy in CASES:
            times = [float(i * FRAME_STRIDE) for i in range(t)]
            frames = torch.from_numpy(to_model_input(frames_u8[:t]))
            features = model.encode(frames)
            ctx, tgt = normalise_batch(times, targets, policy)
            ctx_t, tgt_t = torch.from_numpy(ctx), torch.from_numpy(tgt)
            tensors[f"{name}/features"] = features.numpy()
            tensors[f"{name}/gaussians"] = model.decode_canonical(features, ctx_t, tgt_t).numpy()
            maps = torch.from_numpy(tensors["feature_maps"][:t])
            tensors[f"{name}/gaussian_features"] = model.decode_features(features, ctx_t, tgt_t, maps).numpy()
            index.append({"case": name, "frames": t, "times": times, "targets": targets, "policy": policy})
    # Features are stored for the small cases only, to keep the fixture small; T16 is checked end to end.
    for name in ("T16", "T16_reference", "T4_reference"):
        del tensors[f"{name}/features"]
    save_file({k: np.ascontiguousarray(v) for k, v in tensors.items()}, str(out / "reference.safetensors"))
    meta = {
        "about": "Inputs and outputs of the PyTorch mirror (models/python) for this package; made by c4g.package.fixture.",
        "frames": f"frames_u8 [T, H, W, 3]: bedroom frames {[p.name for p in paths]} centre-cropped and Lanczos-resized by Pillow; model input is (x / 255 - 0.5) / 0.5 in CHW",
        "feature_maps": "feature_maps [T, P, F]: seeded normal noise, the 2D features lifted by feature_decoder.onnx",
        "outputs": "<case>/gaussians [B, N, 14] canonical layout; <case>/gaussian_features [B, N, F]; <case>/features [T, P, C] (small cases only)",
        "cases": index,
    }
    (out / "reference.json").write_text(json.dumps(meta, indent=2) + "\n")


# The decoder-forms fixture: small enough to commit twice over (well under 2 MB in all).
FORMS_CONFIG = C4GConfig(
    dino_dim=16, dino_depth=1, dino_heads=2, patch=7, pos_embed_grid=4,
    aggregator_dim=16, aggregator_depth=1, aggregator_heads=2,
    decoder_dim=32, decoder_heads=2, decoder_head_dim=16, decoder_mlp=64, decoder_depth=2,
    queries=32, time_dim=16, image_size=28, feature_dim=4,
)  # fmt: skip
FORMS_SEED = 5
# (name, context times in seconds, target times), decoded under the stable policy.
FORMS_CASES = [
    ("T1", [0.0], [0.0, 0.0]),
    ("T4", [0.0, 0.5, 1.0, 2.0], [0.0, 0.25, 1.0, 1.7, 2.0]),
]


def build_decoder_forms(out: Path) -> None:
    model = C4G(FORMS_CONFIG)
    random_init(model, seed=FORMS_SEED)
    model.eval()
    provenance = {"kind": "random-init", "seed": FORMS_SEED}
    for form in ("plain", "precomputed"):
        export_package(
            model, out / form, f"decoder-forms-{form}", "0.1.0", provenance,
            f"Test fixture: a very small random model, {form} decoder form.", decoder_form=form,
        )  # fmt: skip
    cfg = FORMS_CONFIG
    rng = np.random.default_rng(FORMS_SEED)
    n_frames = max(len(c[1]) for c in FORMS_CASES)
    frames = rng.uniform(-1.0, 1.0, (n_frames, 3, cfg.image_size, cfg.image_size)).astype(np.float32)
    maps = rng.standard_normal((n_frames, cfg.tokens_per_frame, cfg.feature_dim)).astype(np.float32)
    tensors = {"frames": frames, "feature_maps": maps}
    index = []
    with torch.no_grad():
        for name, times, targets in FORMS_CASES:
            t = len(times)
            features = model.encode(torch.from_numpy(frames[:t]))
            ctx, tgt = (torch.from_numpy(a) for a in normalise_batch(times, targets, "stable"))
            tensors[f"{name}/features"] = features.numpy()
            tensors[f"{name}/gaussians"] = model.decode_canonical(features, ctx, tgt).numpy()
            tensors[f"{name}/gaussian_features"] = model.decode_features(features, ctx, tgt, torch.from_numpy(maps[:t])).numpy()
            index.append({"case": name, "frames": t, "times": times, "targets": targets, "policy": "stable"})
    save_file({k: np.ascontiguousarray(v) for k, v in tensors.items()}, str(out / "reference.safetensors"))
    meta = {
        "about": "One seeded random model (c4g.package.fixture FORMS_CONFIG) exported as plain/ and precomputed/, and the PyTorch mirror's outputs; made by c4g.package.fixture --decoder-forms.",
        "frames": "frames [T, 3, H, W]: seeded uniform noise in [-1, 1], the encoder's input; case k uses the first T",
        "feature_maps": "feature_maps [T, P, F]: seeded normal noise, the 2D features lifted by feature_decoder.onnx",
        "outputs": "<case>/features [T, P, C]; <case>/gaussians [B, N, 14] canonical layout; <case>/gaussian_features [B, N, F]",
        "cases": index,
    }
    (out / "reference.json").write_text(json.dumps(meta, indent=2) + "\n")


# The feature-stream fixture: FORMS_CONFIG's sizes with a stream as wide as the encoder's features.
FEATURE_STREAM_CONFIG = C4GConfig.from_dict({**FORMS_CONFIG.to_dict(), "feature_dim": FORMS_CONFIG.feature_width})
FEATURE_STREAM_SEED = 8


def build_feature_stream(out: Path) -> None:
    cfg = FEATURE_STREAM_CONFIG
    model = C4G(cfg)
    random_init(model, seed=FEATURE_STREAM_SEED)
    model.eval()
    provenance = {"kind": "random-init", "seed": FEATURE_STREAM_SEED}
    export_package(
        model, out, "feature-stream", "0.1.0", provenance,
        "Test fixture: a very small random model whose feature stream lifts its encoder's features.",
        decoder_form="plain", feature_kind="encoder",
    )  # fmt: skip
    rng = np.random.default_rng(FEATURE_STREAM_SEED)
    n_frames = max(len(c[1]) for c in FORMS_CASES)
    frames = rng.uniform(-1.0, 1.0, (n_frames, 3, cfg.image_size, cfg.image_size)).astype(np.float32)
    tensors = {"frames": frames}
    index = []
    with torch.no_grad():
        for name, times, targets in FORMS_CASES:
            t = len(times)
            features = model.encode(torch.from_numpy(frames[:t]))
            ctx, tgt = (torch.from_numpy(a) for a in normalise_batch(times, targets, "stable"))
            gaussians, lifted = model.decode_with_features(features, ctx, tgt, features)
            tensors[f"{name}/features"] = features.numpy()
            tensors[f"{name}/gaussians"] = gaussians.numpy()
            tensors[f"{name}/gaussian_features"] = lifted.numpy()
            index.append({"case": name, "frames": t, "times": times, "targets": targets, "policy": "stable"})
    save_file({k: np.ascontiguousarray(v) for k, v in tensors.items()}, str(out / "reference.safetensors"))
    meta = {
        "about": "One seeded random model (c4g.package.fixture FEATURE_STREAM_CONFIG) with a feature stream of kind 'encoder', and the PyTorch mirror's outputs; made by c4g.package.fixture --feature-stream.",
        "frames": "frames [T, 3, H, W]: seeded uniform noise in [-1, 1], the encoder's input; case k uses the first T",
        "feature_maps": "the kind is 'encoder': feature_decoder.onnx's context_feature_maps are the case's features themselves",
        "outputs": "<case>/features [T, P, C]; <case>/gaussians [B, N, 14] canonical layout (decoder.onnx's, and feature_decoder.onnx's 'gaussians'); <case>/gaussian_features [B, N, F]",
        "cases": index,
    }
    (out / "reference.json").write_text(json.dumps(meta, indent=2) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shared", type=Path, default=Path("../shared"))
    ap.add_argument("--decoder-forms", action="store_true", help="build the decoder-forms fixture instead of c4g-small")
    ap.add_argument("--feature-stream", action="store_true", help="build the feature-stream fixture instead of c4g-small")
    ap.add_argument("--out", type=Path, default=None, help="default: models/fixtures/c4g-small (or decoder-forms, feature-stream)")
    args = ap.parse_args()
    if args.feature_stream:
        out = args.out or Path("models/fixtures/feature-stream")
        build_feature_stream(out)
    elif args.decoder_forms:
        out = args.out or Path("models/fixtures/decoder-forms")
        build_decoder_forms(out)
    else:
        out = args.out or Path("models/fixtures/c4g-small")
        build(args.shared, out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
