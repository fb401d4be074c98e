"""Export tool: checkpoint (official layout) → model package (model.json + ONNX graphs).

    python -m c4g.package.export --checkpoint c4g.ckpt --config official --out models/c4g-official
    python -m c4g.package.export --random-init --seed 0 --config official --out /tmp/c4g-official-random
    python -m c4g.package.export --random-init --config official --precision int8 --out /tmp/c4g-official-int8
    python -m c4g.package.export --random-init --config official --decoder-form plain --out /tmp/c4g-official-plain

The package contract (graph inputs / outputs, canonical Gaussian layout, model.json) is docs/package.md.
Graphs are exported at a fixed input size, so the DINOv2 positional embedding (bicubic, antialiased
resize of the 37 x 37 grid) and the RoPE tables are precomputed constants; T and B stay dynamic.
The conversion to the canonical layout happens inside the decoder graph, and the last decoder layer
computes only the query rows. In the precomputed decoder form (the default from decoder width 512
up, where it is the faster) the package also holds `context_projection.onnx`, the first decoder
layer's qkv projection of the context features, which the engine runs once per clip; the decoder
graph takes its result instead of recomputing it for every target (`c4g.model.precomputed`: the same
result up to float rounding). The decoder also takes `query_indices` (int64 [Q]): it decodes those
queries alone, an approximation the service uses to drop pruned Gaussians from the decoder itself
(`c4g.model.query_subset`). It defaults to every query, so a caller that leaves it out gets the full
decode; `--no-query-subset` writes a decoder without it, as packages made before it.

A model with a feature stream (`--feature-dim`, or a checkpoint that has one) also gets
`feature_decoder.onnx`: the joint two-stream decoder, which takes the context frames' 2D feature
maps as well and returns the per-Gaussian features beside the Gaussians. It takes the features in
both decoder forms (the engine runs it only when features are asked for); `decoder.onnx` stays the
Gaussian stream alone, so a package's Gaussians do not depend on whether it lifts features.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np
import onnx
import torch
from torch import nn

from c4g.model.attention import fused_export
from c4g.model.checkpoint import CheckpointError, feature_dim_of, load_into, read_state_dict, sha256
from c4g.model.config import PRESETS, C4GConfig
from c4g.model.decoder import to_canonical
from c4g.model.init import random_init
from c4g.model.network import C4G
from c4g.model.precomputed import ContextProjection, PrecomputedDecoder
from c4g.model.query_subset import SubsetDecoderGraph, SubsetPrecomputedDecoderGraph
from c4g.model.time_policy import POLICIES
from c4g.raster.reference import FOOTPRINTS

IR_VERSION = 10  # ONNX Runtime 1.31 reads IR <= 13; 10 is what opset 18 needs.
OPSET = 18
TWO_GB = 2**31
DECODER_FORMS = ("precomputed", "plain")
# From this decoder width up the precomputed form is the faster one: the projection it saves grows
# with the width squared, the element-wise work it adds with the width. Measured by c4g.bench.decoder
# (docs/benchmarks.md): at width 128 (c4g-tiny) it is about 25 % slower, at 512 as fast or faster,
# at 2048 (the official model) faster.
PRECOMPUTED_FROM_WIDTH = 512
# What a package's feature stream was trained to lift (`feature_decoder.kind` in model.json): the
# encoder's own patch features (the maps are the encoding's features, F = the feature width), or
# object identity (the maps are one-hot object ids per patch, F = the number of ids).
FEATURE_KINDS = ("encoder", "object-id")
GAUSSIAN_LAYOUT = [
    "x", "y", "z", "scale_x", "scale_y", "scale_z", "rot_w", "rot_x", "rot_y", "rot_z", "opacity", "r", "g", "b",
]  # fmt: skip


class EncoderGraph(nn.Module):
    def __init__(self, model: C4G):
        super().__init__()
        self.model = model
        cfg, agg = model.cfg, model.backbone.aggregator
        grid = cfg.grid
        with torch.no_grad():
            self.register_buffer("pos_embed", agg.patch_embed.interpolated_pos_embed(grid, grid).detach())
            cos, sin = agg.rope.cos_sin(cfg.aggregator_dim // cfg.aggregator_heads, agg.token_positions(grid, grid))
        self.register_buffer("rope_cos", cos)
        self.register_buffer("rope_sin", sin)

    def forward(self, frames: torch.Tensor) -> torch.Tensor:
        return self.model.encode(frames, pos_embed=self.pos_embed, rope=(self.rope_cos, self.rope_sin))


class DecoderGraph(nn.Module):
    def __init__(self, model: C4G):
        super().__init__()
        self.model = model

    def forward(self, features, context_times, target_times) -> torch.Tensor:
        return self.model.decode_canonical(features, context_times, target_times)


class PrecomputedDecoderGraph(nn.Module):
    """The decoder in the precomputed form: the context projection is an input, the query
    constants are baked in."""

    def __init__(self, model: C4G):
        super().__init__()
        self.decoder = PrecomputedDecoder(model)

    def forward(self, features, context_projection, context_times, target_times) -> torch.Tensor:
        return self.decoder.decode_canonical(features, context_projection, context_times, target_times)


class ContextProjectionGraph(nn.Module):
    def __init__(self, model: C4G):
        super().__init__()
        self.projection = ContextProjection(model)

    def forward(self, features) -> torch.Tensor:
        return self.projection(features)


class FeatureDecoderGraph(nn.Module):
    """The joint two-stream decoder: features + times + context feature maps → gaussians (equal to
    decoder.onnx's up to float rounding) and gaussian_features."""

    def __init__(self, model: C4G):
        super().__init__()
        self.model = model

    def forward(self, features, context_times, target_times, context_feature_maps) -> tuple[torch.Tensor, torch.Tensor]:
        return self.model.decode_with_features(features, context_times, target_times, context_feature_maps)


def _export_graph(
    module: nn.Module, args: tuple, path: Path, inputs: dict[str, dict[int, str]], output: dict[str, dict[int, str]], defaults: dict | None = None
) -> None:
    """Export one graph, then rewrite it with the project's IR version, weights outside the .onnx file
    only when they exceed protobuf's 2 GB limit. `defaults` (input name → array) gives inputs a
    value a caller may leave out: an initializer of the same name (ONNX Runtime's overridable
    initializers)."""
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / path.name
        torch.onnx.export(
            module,
            args,
            str(raw),
            input_names=list(inputs),
            output_names=list(output),
            dynamic_axes={**inputs, **output},
            opset_version=OPSET,
            dynamo=False,
            do_constant_folding=True,
        )
        proto = onnx.load(str(raw), load_external_data=True)
    proto.ir_version = IR_VERSION
    proto.producer_name = "c4g-export"
    for name, value in (defaults or {}).items():
        proto.graph.initializer.append(onnx.numpy_helper.from_array(value, name))
    weight_bytes = sum(t.ByteSize() for t in proto.graph.initializer)
    for stale in path.parent.glob(path.name + ".data"):
        stale.unlink()
    if weight_bytes >= TWO_GB - (64 << 20):
        onnx.save_model(proto, str(path), save_as_external_data=True, all_tensors_to_one_file=True, location=path.name + ".data", size_threshold=1024)
    else:
        onnx.save_model(proto, str(path))
    onnx.checker.check_model(str(path))


DECODER_INPUTS = {"features": {0: "T"}, "context_times": {0: "B", 1: "T"}, "target_times": {0: "B"}}


def _example_query_indices(model: C4G) -> torch.Tensor:
    """Traced with fewer queries than the model has (every other one), so that nothing in the graph
    can silently stand for N."""
    return torch.arange(0, model.cfg.queries, 2, dtype=torch.int64)


def _all_queries(model: C4G) -> dict:
    """`query_indices` defaults to every query: a caller that does not feed it (every caller made
    before the input existed) gets the full decode, with the same outputs."""
    return {"query_indices": np.arange(model.cfg.queries, dtype=np.int64)}


def export_plain_decoder(model: C4G, path: Path, query_subset: bool = False) -> None:
    """decoder.onnx in the plain form: features + times (+ query_indices) → gaussians."""
    cfg = model.cfg
    features = torch.zeros(2, cfg.tokens_per_frame, cfg.feature_width)
    args = (features, torch.zeros(2, 2), torch.zeros(2))
    with torch.no_grad():
        if query_subset:
            inputs = {**DECODER_INPUTS, "query_indices": {0: "Q"}}
            graph, output = SubsetDecoderGraph(model), {"gaussians": {0: "B", 1: "Q"}}
            _export_graph(graph, (*args, _example_query_indices(model)), path, inputs, output, _all_queries(model))
        else:
            _export_graph(DecoderGraph(model), args, path, DECODER_INPUTS, {"gaussians": {0: "B"}})


def export_precomputed_decoder(model: C4G, decoder: Path, context_projection: Path, query_subset: bool = False) -> None:
    """The precomputed form: context_projection.onnx (features → context_projection) and a decoder
    that takes it (features + context_projection + times (+ query_indices) → gaussians)."""
    cfg = model.cfg
    features = torch.zeros(2, cfg.tokens_per_frame, cfg.feature_width)
    with torch.no_grad():
        projection = ContextProjectionGraph(model)
        _export_graph(projection, (features,), context_projection, {"features": {0: "T"}}, {"context_projection": {0: "T"}})
        inputs = {"features": {0: "T"}, "context_projection": {0: "T"}, "context_times": {0: "B", 1: "T"}, "target_times": {0: "B"}}
        args = (features, projection(features), torch.zeros(2, 2), torch.zeros(2))
        if query_subset:
            inputs["query_indices"] = {0: "Q"}
            graph, args, output = SubsetPrecomputedDecoderGraph(model), (*args, _example_query_indices(model)), {"gaussians": {0: "B", 1: "Q"}}
            _export_graph(graph, args, decoder, inputs, output, _all_queries(model))
        else:
            _export_graph(PrecomputedDecoderGraph(model), args, decoder, inputs, {"gaussians": {0: "B"}})


def chosen_decoder_form(form: str, cfg: C4GConfig) -> str:
    """`form`, with "auto" resolved: precomputed from `PRECOMPUTED_FROM_WIDTH` up, else plain."""
    if form == "auto":
        return "precomputed" if cfg.decoder_dim >= PRECOMPUTED_FROM_WIDTH else "plain"
    if form not in DECODER_FORMS:
        raise ValueError(f"decoder form {form!r} is not one of {DECODER_FORMS} or 'auto'")
    return form


def declared_feature_kind(kind: str | None, training: dict | None, cfg: C4GConfig) -> str | None:
    """What the feature stream lifts: `kind`, else the training recipe's `features`, else None (not
    declared: random or untrained feature weights lift any F-wide maps equally badly)."""
    kind = kind or (training or {}).get("features")
    if kind in (None, "none"):
        return None
    if kind not in FEATURE_KINDS:
        raise ValueError(f"unknown feature kind {kind!r} (known: {', '.join(FEATURE_KINDS)})")
    if kind == "encoder" and cfg.feature_dim != cfg.feature_width:
        raise ValueError(f"an encoder-feature stream lifts the encoder's {cfg.feature_width}-wide features, not {cfg.feature_dim}-wide ones")
    return kind


def declared_time_policy(training: dict | None) -> str:
    """The `time_policy` a package declares: the one its training recipe names (our own models), else
    frame-step (the official weights, trained on integer frame indices, where frame-step is the reference)."""
    policy = (training or {}).get("time_policy", "frame-step")
    if policy not in POLICIES:
        raise ValueError(f"unknown time policy {policy!r} in the training recipe (known: {', '.join(POLICIES)})")
    return policy


def declared_footprint(training: dict | None) -> str:
    """The rasterizer footprint a package declares (`rasterizer.footprint`, docs/package.md): the one its
    training recipe names, else "ellipse" for our own models (c4g.train.loop, the only source of a recipe,
    renders with c4g.raster.fast's ellipse rule) and "3dgs" for official-layout weights without a recipe
    (an official checkpoint was trained with the original 3DGS rasterizer; random init stands in for one)."""
    footprint = (training or {}).get("footprint", "ellipse" if training is not None else "3dgs")
    if footprint not in FOOTPRINTS:
        raise ValueError(f"unknown footprint {footprint!r} in the training recipe (known: {', '.join(FOOTPRINTS)})")
    return footprint


def export_package(
    model: C4G,
    out: Path,
    name: str,
    version: str,
    provenance: dict,
    description: str = "",
    fused_attention: bool = True,
    training: dict | None = None,
    decoder_form: str = "auto",
    feature_kind: str | None = None,
    query_subset: bool = True,
) -> dict:
    """Write the package for `model` into `out` and return its manifest.

    `fused_attention` exports attention as ONNX Runtime's MultiHeadAttention (flash attention on the
    CPU, fused kernels on CUDA); without it, as plain MatMul / Softmax (any ONNX runtime).
    `decoder_form` "precomputed" adds `context_projection.onnx` and a decoder that takes its output
    (docs/package.md); "plain" writes a decoder that takes the features alone; "auto" picks the
    faster for the model's size (`chosen_decoder_form`). `feature_kind` (or the recipe's `features`)
    is declared as what a feature stream lifts (`FEATURE_KINDS`). `query_subset` gives the decoder its
    `query_indices` input (`c4g.model.query_subset`), declared as `decoder_query_subset`."""
    model = model.eval()
    cfg = model.cfg
    decoder_form = chosen_decoder_form(decoder_form, cfg)
    feature_kind = declared_feature_kind(feature_kind, training, cfg) if model.has_feature_stream else None
    out.mkdir(parents=True, exist_ok=True)
    t, b, p, c = 2, 2, cfg.tokens_per_frame, cfg.feature_width
    frames = torch.zeros(t, 3, cfg.image_size, cfg.image_size)
    features = torch.zeros(t, p, c)
    ctx = torch.zeros(b, t)
    tgt = torch.zeros(b)
    files = {"encoder": "encoder.onnx", "decoder": "decoder.onnx"}
    with torch.no_grad(), fused_export(fused_attention):
        _export_graph(EncoderGraph(model), (frames,), out / files["encoder"], {"frames": {0: "T"}}, {"features": {0: "T"}})
        if decoder_form == "precomputed":
            files["context_projection"] = "context_projection.onnx"
            export_precomputed_decoder(model, out / files["decoder"], out / files["context_projection"], query_subset)
        else:
            export_plain_decoder(model, out / files["decoder"], query_subset)
            (out / "context_projection.onnx").unlink(missing_ok=True)
        if model.has_feature_stream:
            files["feature_decoder"] = "feature_decoder.onnx"
            maps = torch.zeros(t, p, cfg.feature_dim)
            _export_graph(
                FeatureDecoderGraph(model),
                (features, ctx, tgt, maps),
                out / files["feature_decoder"],
                {**DECODER_INPUTS, "context_feature_maps": {0: "T"}},
                {"gaussians": {0: "B"}, "gaussian_features": {0: "B"}},
            )
        elif (out / "feature_decoder.onnx").exists():
            (out / "feature_decoder.onnx").unlink()
    manifest = {
        "format": "c4g-package",
        "format_version": 1,
        "name": name,
        "version": version,
        "description": description,
        "provenance": provenance,
        "input": {
            "height": cfg.image_size,
            "width": cfg.image_size,
            "crop": "center-square",
            "resize": "lanczos3",
            "value_range": [-1.0, 1.0],
        },
        "patch_size": cfg.patch,
        "tokens_per_frame": cfg.tokens_per_frame,
        "feature_width": cfg.feature_width,
        "gaussian_count": cfg.queries,
        "gaussian_layout": GAUSSIAN_LAYOUT,
        "time": {"embedding_dim": cfg.time_dim},
        "time_policy": declared_time_policy(training),
        "precision": "f32",
        "attention": "fused" if fused_attention else "plain",
        "decoder_form": decoder_form,
        **({"decoder_query_subset": True} if query_subset else {}),
        "rasterizer": {"footprint": declared_footprint(training)},
        "files": files,
        "parameters": sum(v.numel() for v in model.state_dict().values()),
        "architecture": cfg.to_dict(),
    }
    if model.has_feature_stream:
        manifest["feature_decoder"] = {"feature_width": cfg.feature_dim}
        if feature_kind is not None:
            manifest["feature_decoder"]["kind"] = feature_kind
    if training is not None:
        manifest["training"] = training
    (out / "model.json").write_text(json.dumps(manifest, indent=2) + "\n")
    readable_by_all(out)
    return manifest


def readable_by_all(package: Path) -> None:
    """Makes every file of the package readable, and its folders enterable, by every user:
    onnx writes external weights (`*.onnx.data`) with mode 0600, which a server running as
    another user (the container images' `c4g`) cannot read. Writable by the owner only."""
    for path in [package, *package.rglob("*")]:
        path.chmod(0o755 if path.is_dir() else 0o644)


def build_model(cfg: C4GConfig, seed: int, checkpoint: Path | None, report: Callable[[str], object] | None = None) -> C4G:
    """The model the tool exports: seeded random weights, overwritten by the checkpoint when given
    (so only what the checkpoint lacks, such as a feature stream, keeps its random weights).
    `report` hears what of the checkpoint is dropped (the official DPT head) and why."""
    model = C4G(cfg)
    random_init(model, seed=seed)
    if checkpoint is not None:
        load_into(model, read_state_dict(checkpoint, report))
    return model.eval()


def _config(arg: str, feature_dim: int | None, checkpoint: Path | None = None) -> C4GConfig:
    """The size preset or JSON config, with the feature stream's width: `feature_dim` when given,
    else the checkpoint's (0 when it has none, or without a checkpoint)."""
    if arg in PRESETS:
        base = PRESETS[arg].to_dict()
    else:
        base = json.loads(Path(arg).read_text())
    if feature_dim is None:
        feature_dim = feature_dim_of(read_state_dict(checkpoint)) if checkpoint is not None and checkpoint.exists() else 0
    base["feature_dim"] = feature_dim
    return C4GConfig.from_dict(base)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.package.export", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--checkpoint", type=Path, help="checkpoint in the official layout (local path)")
    src.add_argument("--random-init", action="store_true", help="random weights (to measure cost at a given size)")
    ap.add_argument("--config", default="official", help=f"size preset ({', '.join(PRESETS)}) or a JSON file of C4GConfig fields")
    ap.add_argument(
        "--feature-dim",
        type=int,
        default=None,
        help="width F of the feature stream (feature lifting; 0: none); default: the checkpoint's (0 without one)",
    )
    ap.add_argument("--feature-kind", choices=FEATURE_KINDS, default=None, help="what the feature stream lifts (declared in model.json)")
    ap.add_argument("--seed", type=int, default=0, help="seed for random weights (the model, or the feature decoder only)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--name", default=None)
    ap.add_argument("--version", default="0.1.0")
    ap.add_argument("--description", default="")
    ap.add_argument("--recipe", type=Path, help="training recipe (JSON, from python -m c4g.train.loop) to record in model.json")
    ap.add_argument(
        "--attention",
        choices=["fused", "plain"],
        default="fused",
        help="fused: ONNX Runtime's MultiHeadAttention (flash attention on CPU); plain: MatMul/Softmax",
    )
    ap.add_argument(
        "--decoder-form",
        choices=["auto", *DECODER_FORMS],
        default="auto",
        help="precomputed: the first decoder layer's projection of the context features runs once per clip "
        f"(context_projection.onnx); plain: the decoder takes the features alone (docs/package.md); auto: "
        f"precomputed from decoder width {PRECOMPUTED_FROM_WIDTH} up, where it is the faster",
    )
    ap.add_argument(
        "--query-subset",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="give the decoder a query_indices input, to decode some of its queries alone (c4g.model.query_subset)",
    )
    ap.add_argument(
        "--precision",
        choices=["f32", "f16", "int8"],
        default="f32",
        help="what the graphs compute in: f16 (weights and activations) or int8 (the large MatMuls); see c4g.package.precision",
    )
    args = ap.parse_args(argv)
    try:
        cfg = _config(args.config, args.feature_dim, args.checkpoint)
    except CheckpointError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    try:
        model = build_model(cfg, args.seed, args.checkpoint, report=lambda line: print(f"note: {line}", file=sys.stderr))
    except (CheckpointError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    if args.checkpoint:
        provenance = {"kind": "checkpoint", "source": args.checkpoint.name, "sha256": sha256(args.checkpoint)}
        if cfg.feature_dim and feature_dim_of(read_state_dict(args.checkpoint)) == 0:
            provenance["feature_decoder"] = f"random init, seed {args.seed} (the checkpoint has none)"
    else:
        provenance = {"kind": "random-init", "seed": args.seed}
    name = args.name or args.out.name
    training = json.loads(args.recipe.read_text()) if args.recipe else None
    manifest = export_package(
        model, args.out, name, args.version, provenance, args.description,
        fused_attention=args.attention == "fused", training=training, decoder_form=args.decoder_form,
        feature_kind=args.feature_kind,
        query_subset=args.query_subset,
    )  # fmt: skip
    if args.precision != "f32":
        from .precision import convert_package

        manifest = convert_package(args.out, args.out, args.precision)
    print(f"wrote {args.out} ({manifest['parameters']:,} parameters, {manifest['precision']}; files: {', '.join(manifest['files'].values())})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
