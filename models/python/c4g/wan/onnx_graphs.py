"""ONNX graphs of diffusers' Wan2.1-VACE classes: the transformer, the VAE encoder and the VAE decoder.

The graphs run diffusers' own modules, traced by PyTorch's TorchScript ONNX exporter (`dynamo=False`:
the torch.export-based exporter folds every `Linear` weight into an anonymous transposed initializer,
which defeats overriding weights by name). Three additions make the trace exportable and usable:

- `aten::rms_norm` (the transformer's QK norm, `torch.nn.RMSNorm`) has no opset-18 symbolic: it is
  written as x / sqrt(mean(x^2) + eps) * weight, in f32 even for an f16 graph.
- `aten::_upsample_nearest_exact2d` (the VAE decoder's 2x upsampling) has none either: it becomes
  `Resize(nearest, half_pixel, round_prefer_ceil)`, which is nearest-exact (src = floor((dst + 0.5) / s)).
- Attention: diffusers' `WanAttnProcessor` calls `dispatch_attention_fn` (SDPA), which the exporter
  writes as MatMul + Softmax + MatMul, materialising heads x L x L scores (~24 GiB per layer in f16 at
  81 x 480 x 832, 32,760 tokens). With `fused=True` the export swaps that one function, for the duration
  of the export only, for ONNX Runtime's `com.microsoft.MultiHeadAttention` (flash / memory-efficient
  kernels on CPU and CUDA). The processor's own code (projections, QK norm, RoPE) is unchanged.

Transformer initializers keep diffusers' parameter names (`blocks.0.attn1.to_q.weight`, [out, in]):
constant folding is off, and so is the exporter's de-duplication of equal initializers (which would
drop the name of, say, a second all-zero bias). ONNX Runtime folds the remaining Transpose nodes when it
loads the graph. RoPE tables are diffusers' float64 buffers, cast to float32 before tracing.

Shapes are fixed at export (the VAE's causal chunk loop over time is unrolled by the trace; RoPE and
patch grids are traced for the given size).
"""

from __future__ import annotations

import contextlib
import tempfile
import warnings
from pathlib import Path

import onnx
import torch
from torch import nn
from torch.onnx import symbolic_helper

from . import c4g_layout

OPSET = 18
IR_VERSION = 10  # ONNX Runtime 1.31 loads IR <= 13; opset 18 needs >= 8. onnx 1.23 would write 14.
TWO_GB = 2**31


# ----------------------------------------------------------------------------- symbolics


def _rms_norm_symbolic(g, x, normalized_shape, weight, eps):
    dims = symbolic_helper._get_const(normalized_shape, "is", "normalized_shape")
    eps_value = symbolic_helper._maybe_get_const(eps, "f")
    eps_value = 1e-6 if symbolic_helper._is_none(eps) else float(eps_value)
    dtype = symbolic_helper._try_get_scalar_type(x)
    half = dtype is not None and dtype in ("Half", "BFloat16")
    y = g.op("Cast", x, to_i=onnx.TensorProto.FLOAT) if half else x
    axes = g.op("Constant", value_t=torch.tensor(list(range(-len(dims), 0)), dtype=torch.int64))
    mean_square = g.op("ReduceMean", g.op("Mul", y, y), axes, keepdims_i=1)
    rms = g.op("Sqrt", g.op("Add", mean_square, g.op("Constant", value_t=torch.tensor(eps_value, dtype=torch.float32))))
    y = g.op("Div", y, rms)
    if half:
        y = g.op("Cast", y, to_i=onnx.TensorProto.FLOAT16 if dtype == "Half" else onnx.TensorProto.BFLOAT16)
    if not symbolic_helper._is_none(weight):
        y = g.op("Mul", y, weight)
    return y


def _nearest_exact_2d_symbolic(g, x, output_size, *args):
    scales = None
    if args and not symbolic_helper._is_none(args[0]):
        scales = symbolic_helper._maybe_get_const(args[0], "fs")
    if scales is None or not isinstance(scales, (list, tuple)):
        out = symbolic_helper._get_const(output_size, "is", "output_size")
        sizes = symbolic_helper._get_tensor_sizes(x)
        scales = [o / i for o, i in zip(out, sizes[-2:])]
    scale_t = g.op("Constant", value_t=torch.tensor([1.0, 1.0, *map(float, scales)], dtype=torch.float32))
    roi = g.op("Constant", value_t=torch.tensor([], dtype=torch.float32))
    return g.op(
        "Resize", x, roi, scale_t, mode_s="nearest", coordinate_transformation_mode_s="half_pixel", nearest_mode_s="round_prefer_ceil"
    )


_SYMBOLICS = {"aten::rms_norm": _rms_norm_symbolic, "aten::_upsample_nearest_exact2d": _nearest_exact_2d_symbolic}


@contextlib.contextmanager
def _symbolics():
    for name, fn in _SYMBOLICS.items():
        torch.onnx.register_custom_op_symbolic(name, fn, OPSET)
    try:
        yield
    finally:
        for name in _SYMBOLICS:
            torch.onnx.unregister_custom_op_symbolic(name, OPSET)


# ----------------------------------------------------------------------------- fused attention


class _MultiHeadAttention(torch.autograd.Function):
    """q [B, Lq, H*D], k, v [B, Lk, H*D] → [B, Lq, H*D]; scale 1/sqrt(D). Exports as the contrib op."""

    @staticmethod
    def forward(ctx, q, k, v, heads: int):  # noqa: ARG004
        def split(t):
            return t.unflatten(2, (heads, -1)).transpose(1, 2)

        return nn.functional.scaled_dot_product_attention(split(q), split(k), split(v)).transpose(1, 2).flatten(2)

    @staticmethod
    def symbolic(g, q, k, v, heads: int):
        return g.op("com.microsoft::MultiHeadAttention", q, k, v, num_heads_i=heads)


def _fused_dispatch(query, key, value, attn_mask=None, dropout_p=0.0, is_causal=False, scale=None, **_):
    """Stands in for diffusers' `dispatch_attention_fn` ([B, L, H, D] in and out) during export."""
    if attn_mask is not None or is_causal or dropout_p or scale is not None:
        raise NotImplementedError("fused export supports plain bidirectional attention only")
    heads = int(query.shape[2])
    out = _MultiHeadAttention.apply(query.flatten(2), key.flatten(2), value.flatten(2), heads)
    return out.unflatten(2, (heads, -1))


@contextlib.contextmanager
def fused_attention(enabled: bool):
    import diffusers.models.transformers.transformer_wan as wan

    original = wan.dispatch_attention_fn
    if enabled:
        wan.dispatch_attention_fn = _fused_dispatch
    try:
        yield
    finally:
        wan.dispatch_attention_fn = original


# ----------------------------------------------------------------------------- graph modules


class TransformerGraph(nn.Module):
    """(latents, timestep, text_embeddings, control, control_scale[, positions]) → velocity, all f32 at
    the edges. For an f16 transformer the inputs are cast to f16 inside the graph and the output back
    to f32. With `positions` (int64 [F'], see c4g_layout.ExplicitTimeRope) each latent frame's
    temporal RoPE index is an input, so one graph serves VACE's layout (0..F'-1) and C4G's."""

    def __init__(self, transformer: nn.Module, positions: bool = False):
        super().__init__()
        self.transformer = transformer
        self.rope = c4g_layout.explicit_positions(transformer) if positions else None

    def forward(self, latents, timestep, text_embeddings, control, control_scale, positions=None):
        if self.rope is not None:
            self.rope.positions = positions
        dtype = self.transformer.dtype
        out = self.transformer(
            hidden_states=latents.to(dtype),
            timestep=timestep,
            encoder_hidden_states=text_embeddings.to(dtype),
            control_hidden_states=control.to(dtype),
            control_hidden_states_scale=control_scale.to(dtype),
            return_dict=False,
        )[0]
        return out.float()


class VaeEncoderGraph(nn.Module):
    """video [1, 3, F, H, W] in [-1, 1] → the posterior mode (mean) [1, 16, F', H/8, W/8], not normalised."""

    def __init__(self, vae: nn.Module):
        super().__init__()
        self.vae = vae

    def forward(self, video):
        return self.vae.encode(video, return_dict=False)[0].mode()


class VaeDecoderGraph(nn.Module):
    """latents [1, 16, F', h, w], not normalised → video [1, 3, F, 8h, 8w], clamped to [-1, 1] by diffusers."""

    def __init__(self, vae: nn.Module):
        super().__init__()
        self.vae = vae

    def forward(self, latents):
        return self.vae.decode(latents, return_dict=False)[0]


def prepare_transformer_for_export(transformer: nn.Module) -> nn.Module:
    """Cast diffusers' float64 RoPE tables to float32 (ONNX Runtime's kernels and the graph are f32)."""
    rope = transformer.rope
    rope = rope.rope if isinstance(rope, c4g_layout.ExplicitTimeRope) else rope
    rope.freqs_cos = rope.freqs_cos.float()
    rope.freqs_sin = rope.freqs_sin.float()
    return transformer


# ----------------------------------------------------------------------------- export


def export_graph(
    module: nn.Module,
    args: tuple,
    path: Path,
    input_names: list[str],
    output_names: list[str],
    strip_prefix: str = "",
    keep_names: bool = True,
    external_data: bool | None = None,
    compact: bool = False,
) -> onnx.ModelProto:
    """Trace `module` into `path` at the example inputs' shapes.

    `keep_names`: no constant folding and no initializer de-duplication, so every parameter keeps its
    name (with `strip_prefix` removed, e.g. "transformer."). `external_data`: weights in `path`.data
    (default: only when they would exceed protobuf's 2 GB limit). `compact`: no node names and short
    intermediate value names (about half the size of a small graph; the fixture uses it)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp, torch.no_grad(), _symbolics(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer warnings on diffusers' shape checks (sizes are fixed)
        raw = Path(tmp) / "graph.onnx"
        torch.onnx.export(
            module,
            args,
            str(raw),
            input_names=input_names,
            output_names=output_names,
            opset_version=OPSET,
            dynamo=False,
            do_constant_folding=not keep_names,
            keep_initializers_as_inputs=keep_names,
        )
        proto = onnx.load(str(raw), load_external_data=True)
    _tidy(proto, strip_prefix)
    if compact:
        _compact(proto)
    weight_bytes = sum(t.ByteSize() for t in proto.graph.initializer)
    for stale in path.parent.glob(path.name + ".data"):
        stale.unlink()
    if external_data is None:
        external_data = weight_bytes >= TWO_GB - (64 << 20)
    if external_data:
        onnx.save_model(
            proto, str(path), save_as_external_data=True, all_tensors_to_one_file=True, location=path.name + ".data", size_threshold=1024
        )
        onnx.checker.check_model(str(path))
    else:
        onnx.save_model(proto, str(path))
        onnx.checker.check_model(proto)
    return proto


def _tidy(proto: onnx.ModelProto, strip_prefix: str) -> None:
    """Initializers are not graph inputs; names lose the wrapper's prefix; the project's IR version."""
    initializers = {t.name for t in proto.graph.initializer}
    inputs = [i for i in proto.graph.input if i.name not in initializers]
    del proto.graph.input[:]
    proto.graph.input.extend(inputs)
    if strip_prefix:
        renamed = {t.name: t.name.removeprefix(strip_prefix) for t in proto.graph.initializer}
        for t in proto.graph.initializer:
            t.name = renamed[t.name]
        for node in proto.graph.node:
            for i, name in enumerate(node.input):
                if name in renamed:
                    node.input[i] = renamed[name]
    proto.ir_version = IR_VERSION
    proto.producer_name = "c4g-wan-export"


def _compact(proto: onnx.ModelProto) -> None:
    """Drop node names and rename intermediate values v0, v1, ... (graph inputs, outputs and
    initializers keep their names; If / Loop subgraphs are renamed consistently)."""
    graph = proto.graph
    keep = {i.name for i in graph.input} | {o.name for o in graph.output} | {t.name for t in graph.initializer}
    renamed: dict[str, str] = {}

    def name_of(name: str) -> str:
        if not name or name in keep:
            return name
        if name not in renamed:
            renamed[name] = f"v{len(renamed)}"
        return renamed[name]

    def walk(g, top: bool) -> None:
        for node in g.node:
            node.name = ""
            node.doc_string = ""
            for i, name in enumerate(node.input):
                node.input[i] = name_of(name)
            for i, name in enumerate(node.output):
                node.output[i] = name_of(name)
            for attr in node.attribute:
                for sub in [attr.g] if attr.HasField("g") else list(attr.graphs):
                    walk(sub, False)
        for info in g.value_info:
            info.name = name_of(info.name)
        if not top:
            for value in list(g.input) + list(g.output):
                value.name = name_of(value.name)

    walk(graph, True)


def export_transformer(
    transformer: nn.Module,
    cfg,
    path: Path,
    fused: bool = True,
    external_data: bool | None = None,
    compact: bool = False,
    positions: bool = True,
) -> onnx.ModelProto:
    """Export `transformer` (a WanVACETransformer3DModel) at `cfg`'s fixed sizes (a RefinerConfig).
    `positions`: temporal RoPE positions as an input (`TransformerGraph`); the tiny VACE fixture's
    graph predates it and is kept without, so both graph kinds stay tested."""
    prepare_transformer_for_export(transformer)
    tcfg = transformer.config
    f, h, w = cfg.latent_frames, cfg.latent_height, cfg.latent_width
    gen = torch.Generator().manual_seed(0)
    device = next(transformer.parameters()).device
    args = (
        torch.randn(1, tcfg.in_channels, f, h, w, generator=gen).to(device),
        torch.tensor([500.0], device=device),
        torch.randn(1, cfg.text_tokens, tcfg.text_dim, generator=gen).to(device),
        torch.randn(1, tcfg.vace_in_channels, f, h, w, generator=gen).to(device),
        torch.ones(len(tcfg.vace_layers), device=device),
    )
    names = ["latents", "timestep", "text_embeddings", "control", "control_scale"]
    if positions:
        args += (torch.arange(f, device=device),)
        names.append("positions")
    with fused_attention(fused):
        return export_graph(
            TransformerGraph(transformer, positions),
            args,
            path,
            names,
            ["velocity"],
            strip_prefix="transformer.",
            keep_names=True,
            external_data=external_data,
            compact=compact,
        )


def export_vae(vae: nn.Module, cfg, encoder_path: Path, decoder_path: Path, compact: bool = False, frame_encoder_path: Path | None = None) -> None:
    """The chunk encoder (`cfg.frames` frames), the decoder (their latents) and, for C4G's layout, the
    one-frame encoder its keyframes go through."""
    device = next(vae.parameters()).device
    gen = torch.Generator().manual_seed(0)
    video = (torch.rand(1, 3, cfg.frames, cfg.height, cfg.width, generator=gen) * 2 - 1).to(device)
    latents = torch.randn(cfg.rendered_latent_shape, generator=gen).to(device)
    export_graph(VaeEncoderGraph(vae), (video,), encoder_path, ["video"], ["latents"], strip_prefix="vae.", keep_names=False, compact=compact)
    export_graph(VaeDecoderGraph(vae), (latents,), decoder_path, ["latents"], ["video"], strip_prefix="vae.", keep_names=False, compact=compact)
    if frame_encoder_path is not None:
        export_graph(VaeEncoderGraph(vae), (video[:, :, :1],), frame_encoder_path, ["video"], ["latents"], strip_prefix="vae.", keep_names=False, compact=compact)
