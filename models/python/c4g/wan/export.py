"""Export tool: Wan2.1-VACE (diffusers' classes) → refiner package (refiner.json + three ONNX graphs, and
optionally umT5's encoder and tokenizer so that workers take captions).

    # the tiny random-weight fixture, with LoRA files and diffusers reference outputs (CPU, ~1 min):
    python -m c4g.wan.export --tiny --out ../fixtures/wan-vace-tiny
    # the real model from a diffusers checkout (Wan-AI/Wan2.1-VACE-1.3B-diffusers layout):
    python -m c4g.wan.export --diffusers /path/to/Wan2.1-VACE-1.3B-diffusers --frames 81 --height 480 --width 832 --out DIR [--fp16] [--device cuda] [--text-encoder]
    # the real architecture with random weights (speed benchmarks):
    python -m c4g.wan.export --random-init --config 1.3b --out DIR [--fp16] [--device cuda]
    # C4G's layout (c4g_layout.py): K keyframe slots before --frames rendered frames:
    python -m c4g.wan.export --tiny --layout c4g --out ../fixtures/wan-vace-tiny-c4g
    python -m c4g.wan.export --diffusers DIR --layout c4g --keyframes 12 --frames 25 ...

Graphs are traced at one fixed video size (frames, height, width, text tokens): see onnx_graphs.py for
how (TorchScript exporter, parameter names kept, fused attention). Weights over 2 GB go to
`<graph>.onnx.data` beside the graph (external data; the 1.3B transformer is ~8.6 GB in f32, ~4.3 GB
in f16). `--fp16` stores the transformer in f16 (diffusers' `_keep_in_fp32_modules` stay f32; RMS norms
compute in f32); its inputs and output stay f32 (cast inside the graph). The VAE graphs are always f32.
Attention is exported as `com.microsoft.MultiHeadAttention` unless `--attention plain` (MatMul +
Softmax: any ONNX runtime, but heads x L x L scores in memory: not usable at 32,760 tokens).
The tiny fixture's graphs are written compact (no node names, intermediate values renamed v0, v1, ...:
half the size); other exports keep the exporter's node names (useful in ONNX Runtime profiles).

Measured ONNX Runtime (CPU) vs diffusers' PyTorch modules on the tiny fixture, f32: transformer ~5e-7,
VAE encoder ~4e-7, VAE decoder ~1e-5 max abs (tests assert 1e-4); f16 transformer ~2e-3 (tests: 2e-2).

## refiner.json
- `format` "c4g-refiner-package", `format_version` 1, `name`.
- `source`: {"kind": "random-init", "seed": S, "config": "tiny" | "1.3b"} or {"kind": "checkpoint", "path": DIR}.
- `frames` F, `height` H, `width` W: the fixed video size of the graphs (in the c4g layout, the
  rendered frames: keyframes come on their own); `fps` 16 (Wan's).
- `layout`: {"kind": "vace"}, or {"kind": "c4g", "keyframes": K, "keyframe_position_offset": 500,
  "rope_positions": 1024, "sampler": {the public code's defaults}}: see c4g_layout.py. The latent
  grid is then K + (F - 1) / 4 + 1 frames; the VAE graphs take and give the rendered part only.
- `latent`: `channels` 16, `frames` F' = (F - 1) / 4 + 1, `height` H / 8, `width` W / 8, `mean` / `std`
  (16 floats each: the VAE's latents_mean / latents_std), `normalise` and `denormalise` (the formulas
  WanVACEPipeline applies: the graphs take and give UN-normalised latents):
  normalised = (mode - mean) * (1 / std) after the encoder graph; decoder input = latents / (1 / std) + mean.
- `patch_size` [1, 2, 2]; `tokens`: F' * (h / 2) * (w / 2), the transformer's sequence length.
- `vace_layers`: the main blocks after which the VACE hints are added (one control_scale entry each).
- `text`: `tokens` L and `dim` D of the text embeddings the transformer takes (umT5: 512 x 4096,
  cut to the real token count and zero-padded); `encoder` (when the package has one): how a caption
  becomes that embedding (see c4g/wan/text.py).
- `control`: how WanVACEPipeline builds the 96-channel control input (see `CONTROL`).
- `timestep`: what the transformer's `timestep` input is (see `TIMESTEP`).
- `sampler`: the defaults (`steps`, `shift`, `guidance_scale`) and the diffusers UniPC config
  (`scheduler`) that the reference pipeline runs use.
- `attention` "fused" | "plain"; `precision` "f32" | "f16" (of the transformer's weights).
- `files`: `transformer`, `vae_encoder`, `vae_decoder` (ONNX file names; `.data` beside them when
  external); `vae_frame_encoder` (c4g layout: one frame [1, 3, 1, H, W] → [1, 16, 1, h, w]); `text_encoder` and `tokenizer` (optional: the umT5 encoder graph and tokenizer.json); `lora` (tiny fixture only): `peft`, `peft_config`, `wan`, `name_map`, `rank`, `alpha`.
- `graphs`: for each ONNX file, its inputs and outputs as {name: [shape]} (f32, but for the
  transformer's `positions`: int64 [F'], each latent frame's temporal RoPE index, VACE's 0..F'-1;
  every export has it but the tiny VACE fixture's, made before it existed).
- `weight_names` "diffusers": transformer initializers are named as diffusers' parameters, [out, in].
- `lora_merged` (only with `--lora`): the LoRA already merged into the transformer's weights, before
  `--fp16` rounded them: `file`, `sha256`, `naming` ("peft" | "wan"), `scale`, `modules` (how many
  weights it adapted). A worker needs no `--lora` for it (another LoRA still merges on top).
- `parameters`: transformer / vae (/ text_encoder) parameter counts; `onnx`: opset and IR version; `diffusers_version`.
- `diffusers_config`: {"transformer": ..., "vae": ...}, the configs the models were built from;
  `text_encoder_config`: the umT5 config (transformers' UMT5Config), when there is an encoder.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import torch

from c4g.package.export import readable_by_all

from . import c4g_layout, onnx_graphs, reference, text
from . import lora as lora_mod
from .configs import PRESETS, TINY, TINY_C4G, RefinerConfig, build_transformer, build_vae

TEXT_ENCODER_FILE = "text_encoder.onnx"
FRAME_ENCODER_FILE = "vae_frame_encoder.onnx"
TOKENIZER_FILE = "tokenizer.json"
LORA_RANK = 4
LORA_ALPHA = 6.0  # scale 1.5: a file that ignores alpha (scale 1) is caught

CONTROL = {
    "channels": 96,
    "layout": ["inactive latents (16)", "reactive latents (16)", "mask (64)"],
    "mask_threshold": 0.5,
    "inactive": "normalise(encode(video * (1 - (mask > 0.5))))",
    "reactive": "normalise(encode(video * (mask > 0.5)))",
    "video": "frames in [0, 1] * 2 - 1, [1, 3, F, H, W]",
    "mask_channels": (
        "the mask in [0, 1] (NOT thresholded here), [F, H, W] viewed as [F, H/8, 8, W/8, 8], "
        "channel = dy * 8 + dx, then resized in time F -> F' with nearest-exact: latent frame j takes "
        "source frame floor((j + 0.5) * F / F')"
    ),
}

TIMESTEP = {
    "input": "timestep f32 [1]",
    "value": "what diffusers feeds: the scheduler's timestep t, not sigma",
    "unipc": "t = floor(sigma * 1000) (sigma the shifted sigma in f64; diffusers keeps t as int64, the model casts it to f32)",
    "flow_match_euler": "t = sigma * 1000 (f32, not rounded)",
    "num_train_timesteps": 1000,
}


def graph_signatures(cfg: RefinerConfig, positions: bool = True) -> dict:
    f, h, w = cfg.latent_frames, cfg.latent_height, cfg.latent_width
    n_vace = len(cfg.transformer["vace_layers"])
    latent = [1, 16, f, h, w]
    chunk = cfg.rendered_latent_shape
    video = [1, 3, cfg.frames, cfg.height, cfg.width]
    graphs = {
        "transformer": {
            "inputs": {
                "latents": latent,
                "timestep": [1],
                "text_embeddings": [1, cfg.text_tokens, cfg.transformer["text_dim"]],
                "control": [1, cfg.transformer["vace_in_channels"], f, h, w],
                "control_scale": [n_vace],
                **({"positions": [f]} if positions else {}),
            },
            "outputs": {"velocity": latent},
        },
        "vae_encoder": {"inputs": {"video": video}, "outputs": {"latents": chunk}},
        "vae_decoder": {"inputs": {"latents": chunk}, "outputs": {"video": video}},
    }
    if cfg.keyframes:
        graphs["vae_frame_encoder"] = {"inputs": {"video": [1, 3, 1, cfg.height, cfg.width]}, "outputs": {"latents": [1, 16, 1, h, w]}}
    return graphs


def layout_entry(cfg: RefinerConfig) -> dict:
    """refiner.json `layout`: how a run's latent frames are laid out (see the module doc)."""
    if not cfg.keyframes:
        return {"kind": "vace"}
    return {
        "kind": "c4g",
        "keyframes": cfg.keyframes,
        "keyframe_position_offset": c4g_layout.KEYFRAME_POSITION_OFFSET,
        "rope_positions": cfg.transformer["rope_max_seq_len"],
        "sequence": "[K keyframes, each VAE-encoded alone ; the rendered frames padded to `frames` by repeating the last, one chunk]",
        "positions": "keyframe: source-frame index + keyframe_position_offset; rendered latent frame j: j",
        "sampler": {"solver": "euler", "schedule": "diffsynth", **c4g_layout.DEFAULTS},
    }


def manifest(
    cfg: RefinerConfig,
    source: dict,
    attention: str,
    precision: str,
    counts: dict,
    lora: dict | None = None,
    text_encoder: dict | None = None,
    positions: bool = True,
) -> dict:
    """refiner.json. `text_encoder`: the umT5 config when the package has the encoder and tokenizer."""
    mean, std = cfg.vae["latents_mean"], cfg.vae["latents_std"]
    files = {"transformer": "transformer.onnx", "vae_encoder": "vae_encoder.onnx", "vae_decoder": "vae_decoder.onnx"}
    if cfg.keyframes:
        files["vae_frame_encoder"] = FRAME_ENCODER_FILE
    graphs = graph_signatures(cfg, positions)
    text_spec: dict = {"tokens": cfg.text_tokens, "dim": cfg.transformer["text_dim"]}
    if text_encoder is not None:
        files["text_encoder"] = TEXT_ENCODER_FILE
        files["tokenizer"] = TOKENIZER_FILE
        graphs["text_encoder"] = text.graph_signature(cfg.text_tokens, cfg.transformer["text_dim"])
        text_spec["encoder"] = text.manifest_entry(cfg.text_tokens)
    if lora is not None:
        files["lora"] = lora
    return {
        "format": "c4g-refiner-package",
        "format_version": 1,
        "name": cfg.name,
        "source": source,
        "frames": cfg.frames,
        "height": cfg.height,
        "width": cfg.width,
        "fps": cfg.fps,
        "latent": {
            "channels": 16,
            "frames": cfg.latent_frames,
            "height": cfg.latent_height,
            "width": cfg.latent_width,
            "mean": list(mean),
            "std": list(std),
            "normalise": "(mode - mean) * (1 / std)",
            "denormalise": "latents / (1 / std) + mean",
            "temporal_compression": 4,
            "spatial_compression": 8,
        },
        "layout": layout_entry(cfg),
        "patch_size": list(cfg.transformer["patch_size"]),
        "tokens": cfg.tokens,
        "vace_layers": list(cfg.transformer["vace_layers"]),
        "text": text_spec,
        "control": CONTROL,
        "timestep": TIMESTEP,
        "sampler": {"steps": cfg.steps, "shift": cfg.shift, "guidance_scale": cfg.guidance_scale, "scheduler": {"class": "UniPCMultistepScheduler", **cfg.scheduler}},
        "attention": attention,
        "precision": precision,
        "files": files,
        "graphs": graphs,
        "weight_names": "diffusers",
        "parameters": counts,
        "onnx": {"opset": onnx_graphs.OPSET, "ir_version": onnx_graphs.IR_VERSION},
        "diffusers_version": reference._diffusers_version(),
        "diffusers_config": {"transformer": _jsonable(cfg.transformer), "vae": _jsonable(cfg.vae)},
        **({"text_encoder_config": _jsonable(text_encoder)} if text_encoder is not None else {}),
    }


def _jsonable(d: dict) -> dict:
    return json.loads(json.dumps({k: (list(v) if isinstance(v, tuple) else v) for k, v in d.items() if not k.startswith("_")}))


def _config_dict(model) -> dict:
    return _jsonable(dict(model.config))


def to_fp16(transformer: torch.nn.Module) -> torch.nn.Module:
    """f16 weights, except what diffusers keeps in f32 (`_keep_in_fp32_modules`: RoPE, time embedder,
    modulation tables, the layer norms), as `from_pretrained(torch_dtype=torch.float16)` does."""
    keep = set(getattr(transformer, "_keep_in_fp32_modules", None) or [])
    for name, p in transformer.named_parameters():
        if not keep & set(name.split(".")):
            p.data = p.data.half()
    return transformer


# ----------------------------------------------------------------------------- packages


def export_models(
    transformer, vae, cfg: RefinerConfig, out: Path, attention: str, external_data: bool | None = None, compact: bool = False, positions: bool = True
) -> None:
    out.mkdir(parents=True, exist_ok=True)
    onnx_graphs.export_transformer(
        transformer, cfg, out / "transformer.onnx", fused=attention == "fused", external_data=external_data, compact=compact, positions=positions
    )
    frame_encoder = out / FRAME_ENCODER_FILE if cfg.keyframes else None
    onnx_graphs.export_vae(vae, cfg, out / "vae_encoder.onnx", out / "vae_decoder.onnx", compact=compact, frame_encoder_path=frame_encoder)


def export_tiny(out: Path, seed: int = 0, attention: str = "fused") -> dict:
    """The fixture package: graphs, refiner.json, LoRA files and diffusers reference outputs."""
    cfg = TINY
    cfg.validate()
    out.mkdir(parents=True, exist_ok=True)
    transformer = build_transformer(cfg.transformer, seed)
    vae = build_vae(cfg.vae, seed)

    # LoRA: random factors, both namings, checked against diffusers' own loading.
    targets = lora_mod.tiny_targets(cfg.transformer)
    factors = lora_mod.random_lora(transformer, targets, LORA_RANK, LORA_ALPHA, seed + 2)
    modules = dict(transformer.named_modules())
    shapes = {t: list(modules[t].weight.shape) for t in targets}
    lora_mod.write_lora_files(factors, LORA_RANK, LORA_ALPHA, out / "lora", shapes)
    lora_transformer = load_peft_lora_with_diffusers(transformer, vae, out / "lora" / "peft")
    check_lora_files(transformer, lora_transformer, out / "lora")

    # Reference outputs from the stock PyTorch models (float64 RoPE tables, as diffusers runs them).
    ref = out / "reference"
    ref.mkdir(parents=True, exist_ok=True)
    reference.write_json(ref / "sampler.json", reference.sampler_reference())
    inputs = reference.fixture_inputs(cfg, seed + 3)
    runs = {
        "pipeline_unipc": (transformer, reference.unipc(cfg.shift)),
        "pipeline_euler": (transformer, reference.euler(cfg.shift)),
        "pipeline_unipc_lora": (lora_transformer, reference.unipc(cfg.shift)),
    }
    for name, (model, scheduler) in runs.items():
        reference.save_npz(ref / f"{name}.npz", reference.run_pipeline(model, vae, scheduler, cfg, inputs, cfg.guidance_scale))
    reference.save_npz(ref / "transformer.npz", reference.transformer_case(transformer, cfg, seed + 4))
    reference.save_npz(ref / "vae.npz", reference.vae_case(vae, cfg, seed + 5))

    # The text side: a tiny umT5 and tokenizer, and captions through the pipeline's encode_prompt.
    text_encoder = text.build_text_encoder(text.UMT5_TINY, seed + 6)
    text.tiny_tokenizer().save(str(out / TOKENIZER_FILE))
    text_ref, text_arrays = reference.text_case(text.fast_tokenizer(out / TOKENIZER_FILE), text_encoder, cfg.text_tokens)
    reference.write_json(ref / "text.json", text_ref)
    reference.save_npz(ref / "text.npz", text_arrays)
    text.export_text_encoder(text_encoder, cfg.text_tokens, out / TEXT_ENCODER_FILE, compact=True)

    # Exported without temporal positions, as it was before they existed (the c4g fixture has them).
    export_models(copy.deepcopy(transformer), copy.deepcopy(vae), cfg, out, attention, compact=True, positions=False)
    counts = {
        "transformer": sum(p.numel() for p in transformer.parameters()),
        "vae": sum(p.numel() for p in vae.parameters()),
        "text_encoder": sum(p.numel() for p in text_encoder.parameters()),
    }
    lora_files = {
        "peft": "lora/peft/adapter_model.safetensors",
        "peft_config": "lora/peft/adapter_config.json",
        "wan": "lora/wan/lora.safetensors",
        "name_map": "lora/name_map.json",
        "rank": LORA_RANK,
        "alpha": LORA_ALPHA,
    }
    meta = manifest(cfg, {"kind": "random-init", "seed": seed, "config": "tiny"}, attention, "f32", counts, lora_files, text.UMT5_TINY, positions=False)
    meta["diffusers_config"] = {"transformer": _config_dict(transformer), "vae": _config_dict(vae)}
    (out / "refiner.json").write_text(json.dumps(meta, indent=2) + "\n")
    (out / "README.md").write_text(package_readme(meta))
    (ref / "README.md").write_text(reference_readme(cfg, seed))
    return meta


def export_tiny_c4g(out: Path, seed: int = 0, attention: str = "fused") -> dict:
    """The C4G-layout fixture package: the tiny fixture's weights (same seed), graphs at 3 keyframes +
    5 rendered frames with temporal positions as an input, and c4g_layout.py's reference outputs."""
    cfg = TINY_C4G
    cfg.validate()
    out.mkdir(parents=True, exist_ok=True)
    transformer = build_transformer(cfg.transformer, seed)
    vae = build_vae(cfg.vae, seed)
    ref = out / "reference"
    ref.mkdir(parents=True, exist_ok=True)
    inputs = c4g_layout.fixture_inputs(cfg, seed + 3, rendered_frames=cfg.frames - 1)
    run = c4g_layout.run(transformer, vae, cfg, inputs, cfg.steps, cfg.shift, cfg.guidance_scale)
    reference.save_npz(ref / "pipeline_c4g.npz", run)
    reference.save_npz(ref / "transformer_positions.npz", transformer_positions_case(transformer, cfg, seed + 4))
    reference.save_npz(ref / "vae_frame.npz", c4g_layout.frame_encoder_case(vae, cfg, seed + 5))
    export_models(copy.deepcopy(transformer), copy.deepcopy(vae), cfg, out, attention, compact=True)
    counts = {"transformer": sum(p.numel() for p in transformer.parameters()), "vae": sum(p.numel() for p in vae.parameters())}
    meta = manifest(cfg, {"kind": "random-init", "seed": seed, "config": "tiny-c4g"}, attention, "f32", counts)
    (out / "refiner.json").write_text(json.dumps(meta, indent=2) + "\n")
    (out / "README.md").write_text(package_readme(meta))
    (ref / "README.md").write_text(c4g_reference_readme(cfg, seed, inputs))
    return meta


def transformer_positions_case(transformer, cfg: RefinerConfig, seed: int) -> dict:
    """Random inputs and C4G positions (keyframes at 500, 503, 509; rendered 0, 1) → velocity."""
    gen = torch.Generator().manual_seed(seed)
    f, h, w = cfg.latent_frames, cfg.latent_height, cfg.latent_width
    n_vace = len(cfg.transformer["vace_layers"])
    case = {
        "latents": torch.randn(1, 16, f, h, w, generator=gen),
        "timestep": torch.tensor([937.5]),
        "text_embeddings": torch.randn(1, cfg.text_tokens, cfg.transformer["text_dim"], generator=gen),
        "control": torch.randn(1, cfg.transformer["vace_in_channels"], f, h, w, generator=gen),
        "control_scale": torch.ones(n_vace),
        "positions": c4g_layout.positions([0, 3, 9][: cfg.keyframes], cfg.rendered_latent_frames),
    }
    v = c4g_layout.velocity(
        transformer, case["latents"], float(case["timestep"][0]), case["text_embeddings"], case["control"], case["positions"]
    )
    return {**{k: t.numpy() for k, t in case.items()}, "velocity": v.numpy()}


def load_peft_lora_with_diffusers(transformer, vae, peft_dir: Path):
    """A copy of `transformer` with the PEFT LoRA loaded by diffusers' `load_lora_weights` and fused at
    scale 1.0 (what the LoRA reference pipeline runs)."""
    from diffusers import WanVACEPipeline

    model = copy.deepcopy(transformer)
    pipe = WanVACEPipeline(tokenizer=None, text_encoder=None, vae=vae, scheduler=reference.unipc(3.0), transformer=model)
    pipe.load_lora_weights(str(peft_dir), weight_name="adapter_model.safetensors", adapter_name="c4g")
    pipe.fuse_lora(components=["transformer"], lora_scale=1.0)
    pipe.unload_lora_weights()  # keeps the fused weights, drops the adapter layers
    return model.eval()


def check_lora_files(base, fused, lora_dir: Path, atol: float = 1e-6) -> None:
    """Both files carry the same deltas, and diffusers' fused weights are base + delta. diffusers'
    converter for Wan-named LoRAs must agree too, on the keys it can convert (not the VACE ones)."""
    config = json.loads((lora_dir / "peft" / "adapter_config.json").read_text())
    peft = lora_mod.deltas_from_peft(lora_dir / "peft" / "adapter_model.safetensors", config)
    wan = lora_mod.deltas_from_wan(lora_dir / "wan" / "lora.safetensors")
    if peft.keys() != wan.keys():
        raise AssertionError(f"LoRA files target different modules: {sorted(peft.keys() ^ wan.keys())}")
    base_sd, fused_sd = base.state_dict(), fused.state_dict()
    for name, delta in peft.items():
        if (delta - wan[name]).abs().max() > atol:
            raise AssertionError(f"{name}: PEFT and Wan deltas differ")
        merged = base_sd[name].double() + delta
        err = (merged - fused_sd[name].double()).abs().max()
        if err > 1e-5:
            raise AssertionError(f"{name}: diffusers' fused weight differs from W + scale * B @ A by {err}")
    changed = [k for k in base_sd if not torch.equal(base_sd[k], fused_sd[k])]
    if sorted(changed) != sorted(peft):
        raise AssertionError(f"diffusers changed {sorted(set(changed) ^ set(peft))} unexpectedly")
    from diffusers.loaders.lora_conversion_utils import _convert_non_diffusers_wan_lora_to_diffusers
    from safetensors.torch import load_file

    wan_sd = load_file(str(lora_dir / "wan" / "lora.safetensors"))
    converted = _convert_non_diffusers_wan_lora_to_diffusers({k: v for k, v in wan_sd.items() if ".vace_blocks." not in k})
    for key, a in converted.items():
        if key.endswith(".lora_A.weight"):
            module = key.removeprefix("transformer.").removesuffix(".lora_A.weight")
            delta = converted[key.replace("lora_A", "lora_B")].double() @ a.double()  # alpha folded in by diffusers
            if (delta - peft[f"{module}.weight"]).abs().max() > atol:
                raise AssertionError(f"{module}: diffusers reads the Wan-named file differently")


def export_real(args) -> dict:
    if args.diffusers:
        from diffusers import AutoencoderKLWan, WanVACETransformer3DModel

        root = Path(args.diffusers)
        # With a LoRA, load in f32, merge, then round (to_fp16 keeps what from_pretrained(f16) keeps).
        dtype = torch.float16 if args.fp16 and not args.lora else torch.float32
        transformer = WanVACETransformer3DModel.from_pretrained(root, subfolder="transformer", torch_dtype=dtype).eval()
        vae = AutoencoderKLWan.from_pretrained(root, subfolder="vae", torch_dtype=torch.float32).eval()
        sched_path = root / "scheduler" / "scheduler_config.json"
        scheduler = json.loads(sched_path.read_text()) if sched_path.exists() else dict(PRESETS["1.3b"].scheduler)
        source = {"kind": "checkpoint", "path": str(root)}
        base = PRESETS["1.3b"]
    else:
        base = PRESETS[args.config]
        transformer = build_transformer(base.transformer, args.seed)
        vae = build_vae(base.vae, args.seed)
        scheduler = dict(base.scheduler)
        source = {"kind": "random-init", "seed": args.seed, "config": args.config}
    lora_merged = lora_mod.merge_into_transformer(transformer, Path(args.lora), args.lora_scale) if args.lora else None
    if args.fp16 and (args.lora or not args.diffusers):
        to_fp16(transformer)
    transformer_cfg, vae_cfg = _config_dict(transformer), _config_dict(vae)
    shift = float(scheduler.get("flow_shift", base.shift))
    cfg = RefinerConfig(
        name=args.name or (base.name if not args.diffusers else Path(args.diffusers).name.lower()),
        transformer=transformer_cfg,
        vae=vae_cfg,
        frames=args.frames or base.frames,
        height=args.height or base.height,
        width=args.width or base.width,
        text_tokens=args.text_tokens or base.text_tokens,
        shift=c4g_layout.DEFAULTS["shift"] if args.layout == "c4g" else shift,
        steps=c4g_layout.DEFAULTS["steps"] if args.layout == "c4g" else base.steps,
        keyframes=args.keyframes if args.layout == "c4g" else 0,
        scheduler={**({"class": scheduler["_class_name"]} if "_class_name" in scheduler else {}), **{k: v for k, v in scheduler.items() if not k.startswith("_")}},
    )
    cfg.validate()
    transformer.to(args.device)
    vae.to(args.device)
    out = Path(args.out)
    external = True if args.external_data else None
    export_models(transformer, vae, cfg, out, args.attention, external)
    counts = {"transformer": sum(p.numel() for p in transformer.parameters()), "vae": sum(p.numel() for p in vae.parameters())}
    text_config = None
    if args.text_encoder:
        encoder, text_config = export_real_text_encoder(args, cfg, out)
        counts["text_encoder"] = sum(p.numel() for p in encoder.parameters())
    meta = manifest(cfg, source, args.attention, "f16" if args.fp16 else "f32", counts, text_encoder=text_config)
    if lora_merged is not None:
        meta["lora_merged"] = lora_merged
    (out / "refiner.json").write_text(json.dumps(meta, indent=2) + "\n")
    (out / "README.md").write_text(package_readme(meta))
    return meta


def export_real_text_encoder(args, cfg: RefinerConfig, out: Path):
    """umT5's encoder (f32: umT5 overflows in f16) and tokenizer: from the checkout's text_encoder/ and
    tokenizer/, or random weights at umT5-XXL's size with the tiny tokenizer (speed only)."""
    if args.diffusers:
        from transformers import AutoTokenizer, UMT5EncoderModel

        root = Path(args.diffusers)
        encoder = UMT5EncoderModel.from_pretrained(root / "text_encoder", torch_dtype=torch.float32).eval()
        AutoTokenizer.from_pretrained(root / "tokenizer").backend_tokenizer.save(str(out / TOKENIZER_FILE))
    else:
        encoder = text.build_text_encoder(text.UMT5_XXL if args.config == "1.3b" else text.UMT5_TINY, args.seed + 6)
        text.tiny_tokenizer().save(str(out / TOKENIZER_FILE))
    if encoder.config.d_model != cfg.transformer["text_dim"]:
        raise ValueError(f"the text encoder is {encoder.config.d_model} wide; the transformer takes {cfg.transformer['text_dim']}")
    encoder.to(args.device)
    text.export_text_encoder(encoder, cfg.text_tokens, out / TEXT_ENCODER_FILE, external_data=True if args.external_data else None)
    return encoder, {key: getattr(encoder.config, key) for key in text.UMT5_XXL}


# ----------------------------------------------------------------------------- READMEs


def package_readme(meta: dict) -> str:
    g = meta["graphs"]

    def sig(graph):
        ins = ", ".join(f"`{k}` {v}" for k, v in g[graph]["inputs"].items())
        outs = ", ".join(f"`{k}` {v}" for k, v in g[graph]["outputs"].items())
        return f"- `{meta['files'][graph]}`: {ins} → {outs}"

    source = meta["source"]
    remake = (
        "`python -m c4g.wan.export --tiny --out ../fixtures/wan-vace-tiny` (from models/python; deterministic: fixed seeds, CPU)"
        if source.get("config") == "tiny"
        else "see `python -m c4g.wan.export --help`"
    )
    lines = [
        f"# {meta['name']}: Wan2.1-VACE refiner package",
        "",
        "Built by `c4g.wan.export` from diffusers' `WanVACETransformer3DModel` and `AutoencoderKLWan`"
        + (" with random weights (a CPU-sized stand-in for Wan2.1-VACE-1.3B: same structure, tiny widths)." if source["kind"] == "random-init" else f" loaded from `{source.get('path')}`."),
        "",
        f"Remake: {remake}. Every field of refiner.json is documented in `c4g/wan/export.py`.",
        "",
        f"Video {meta['frames']} frames x {meta['height']} x {meta['width']} → latents 16 x {meta['latent']['frames']} x {meta['latent']['height']} x {meta['latent']['width']} ({meta['tokens']} tokens); text {meta['text']['tokens']} x {meta['text']['dim']}; VACE layers {meta['vace_layers']}.",
        "",
        "## Graphs (all f32 at the edges, fixed shapes)",
        sig("transformer"),
        sig("vae_encoder"),
        sig("vae_decoder"),
        *([sig("text_encoder"), f"- `{meta['files']['tokenizer']}`: the umT5 tokenizer (Hugging Face tokenizers JSON)."] if "text_encoder" in meta["files"] else []),
        "",
        "- `timestep` is the scheduler's timestep as diffusers feeds it: floor(sigma * 1000) with UniPC, sigma * 1000 with FlowMatchEuler.",
        "- The VAE graphs take and give UN-normalised latents: normalised = (mode - mean) * (1 / std); decoder input = latents / (1 / std) + mean.",
        f"- Transformer initializers are diffusers' parameter names ([out, in] for linears); attention is `{meta['attention']}`"
        + (" (com.microsoft.MultiHeadAttention)." if meta["attention"] == "fused" else " (MatMul + Softmax)."),
        "- `control` = [inactive latents 16; reactive latents 16; mask 64]; see refiner.json `control`.",
    ]
    if "lora" in meta["files"]:
        lora = meta["files"]["lora"]
        lines += [
            "",
            "## LoRA (rank {rank}, alpha {alpha}: scale {scale})".format(rank=lora["rank"], alpha=lora["alpha"], scale=lora["alpha"] / lora["rank"]),
            "- `lora/peft/adapter_model.safetensors` + `adapter_config.json`: `transformer.<diffusers module>.lora_A.weight` [r, in], `.lora_B.weight` [out, r].",
            "- `lora/wan/lora.safetensors`: the same LoRA as `diffusion_model.<Wan module>.lora_down.weight`, `.lora_up.weight`, `.alpha` (0-d).",
            "- `lora/name_map.json`: per module, Wan name → diffusers name → ONNX initializer (+ shape), and the renaming rules.",
            "- Merge: W += alpha / r * B @ A. Checked at export: both files give the same deltas, and diffusers' `load_lora_weights` + `fuse_lora` gives W + delta.",
            "",
            "## Reference outputs",
            "`reference/`: see reference/README.md.",
        ]
    return "\n".join(lines) + "\n"


def reference_readme(cfg: RefinerConfig, seed: int) -> str:
    f, h, w = cfg.latent_frames, cfg.latent_height, cfg.latent_width
    lat = f"[1, 16, {f}, {h}, {w}]"
    L, D = cfg.text_tokens, cfg.transformer["text_dim"]
    S = cfg.steps
    r0, r1, c0, c1 = reference.KEEP_BOX
    return f"""# Reference outputs (diffusers {reference._diffusers_version()}, PyTorch, CPU, float32)

Made by `python -m c4g.wan.export --tiny` (c4g/wan/reference.py), seed {seed}, from the same random-weight
models as the ONNX graphs, run as stock diffusers modules (float64 RoPE tables; the ONNX graphs use
float32 ones). All arrays float32 unless noted. Latents are [1, 16, F', h, w] = {lat}.

## sampler.json
For (steps, shift) in {reference.SAMPLER_CASES}: `sigmas` (steps + 1, ending in 0) and `timesteps` (steps) of
`FlowMatchEulerDiscreteScheduler(shift=shift)` and of `UniPCMultistepScheduler(prediction_type="flow_prediction",
use_flow_sigmas=True, flow_shift=shift)` (otherwise defaults: solver_order 2, bh2, predict_x0, lower_order_final,
final_sigmas_type "zero"), each with its full config.

diffusers differs from WAN_VACE.md's test vector (the original Wan code: base sigmas linspace(0.999, 0, 5)[:-1] →
[0.9998, 0.937265, 0.833055, 0.624687], timesteps [999, 937, 833, 624]):
- UniPC: base sigmas linspace(1, 1/1000, steps + 1)[:-1], shifted, the first minus 1e-6 → for 4 steps / shift 5
  [0.999999, 0.937578, 0.833611, 0.625936, 0]; timesteps are int64 floor(sigma * 1000): [999, 937, 833, 625].
- FlowMatchEuler: timesteps linspace(1000, 1000 * shifted(1/1000), steps), and sigmas = shifted(timesteps / 1000), so
  the shift is applied twice at the low end: for 4 steps / shift 5 sigmas [1, 0.909707, 0.717317, 0.024414, 0],
  timesteps sigma * 1000 as f32 (not rounded).

## pipeline_unipc.npz, pipeline_euler.npz, pipeline_unipc_lora.npz
`WanVACEPipeline(tokenizer=None, text_encoder=None, ...)` called with video (PIL RGB frames), mask (PIL "L" frames,
0 / 255), prompt_embeds, negative_prompt_embeds, latents=noise, height {cfg.height}, width {cfg.width}, num_frames {cfg.frames},
num_inference_steps {S}, guidance_scale {cfg.guidance_scale}, conditioning_scale 1.0, scheduler shift {cfg.shift}; once with
output_type="latent" and once with output_type="np" (identical transformer calls, checked).
- unipc: UniPCMultistepScheduler (the pipeline's default kind) as above; euler: FlowMatchEulerDiscreteScheduler;
  unipc_lora: UniPC, with lora/peft loaded by `pipe.load_lora_weights(lora/peft, weight_name="adapter_model.safetensors")`,
  then `fuse_lora(lora_scale=1.0)` (scale alpha / r = {LORA_ALPHA / LORA_RANK} from the header metadata).

Files are `np.savez_compressed` archives. Keys:
- inputs: `video` [F, H, W, 3] = [{cfg.frames}, {cfg.height}, {cfg.width}, 3] in [0, 1] (uint8 / 255); `mask` [F, H, W] in {{0, 1}}:
  frames 0..{reference.CONTEXT_FRAMES - 1} are 0 (context: keep), later frames 1 (regenerate) except rows {r0}..{r1 - 1} x cols {c0}..{c1 - 1}
  (0: keep; the box edges cut 8 x 8 blocks, so the 64 mask channels differ); `prompt_embeds`, `negative_prompt_embeds`
  [1, {L}, {D}] (zero after the first {2 * L // 3} / {L // 3} tokens); `noise` {lat} (the `latents=` argument).
- `inactive_latents_raw`, `reactive_latents_raw` {lat}: VAE posterior modes (un-normalised) of video * (1 - m) and
  video * m, m = mask > 0.5, video = frames * 2 - 1 as [1, 3, F, H, W] (the encoder graph's outputs for these inputs).
- `control` [1, 96, {f}, {h}, {w}]: the control tensor the pipeline passed to the transformer (hooked).
- `sigmas` [{S + 1}]: the scheduler's sigmas; `timesteps` [{S}]: the timestep the transformer received at each step.
- `velocity_first` {lat}: the transformer's output on its first call (step 0, conditional prompt).
- `step_latents` [{S}, 1, 16, {f}, {h}, {w}]: the latents entering each step; `step_velocity_cond` / `step_velocity_uncond`
  [{S}, 1, 16, {f}, {h}, {w}]: the two transformer outputs of each step (guided = uncond + g * (cond - uncond)).
- `latents_final` {lat}: output_type="latent" result (normalised latent space).
- `decoder_input` {lat}: what the VAE decoder received (latents_final / (1 / std) + mean).
- `frames_out` [F, H, W, 3]: the output_type="np" result: decoder output (in [-1, 1], [1, 3, F, H, W]) / 2 + 0.5,
  clamped to [0, 1], as [F, H, W, 3].
- scalars: `guidance_scale`, `shift`, `steps` (int64); `conditioning_scale` [{len(cfg.transformer['vace_layers'])}].

## transformer.npz
Stock PyTorch transformer on random inputs: `latents` {lat}, `timestep` [1] (937.0), `text_embeddings` [1, {L}, {D}],
`control` [1, 96, {f}, {h}, {w}], `control_scale` [{len(cfg.transformer['vace_layers'])}] ({reference.CONTROL_SCALE}) → `velocity` {lat}.

## vae.npz
`video` [1, 3, F, H, W] uniform in [-1, 1] → `latents_mode` {lat} (posterior mode, un-normalised);
`latents` {lat} standard normal → `video_decoded` [1, 3, F, H, W].

## text.json, text.npz
Captions through `WanVACEPipeline(tokenizer=T5TokenizerFast(tokenizer.json), text_encoder=UMT5EncoderModel
(tiny, random weights)).encode_prompt(prompt, max_sequence_length={L})` (ftfy installed, as prompt_clean needs).
- text.json `cases`: per caption (c4g/wan/reference.py `CAPTIONS`): `caption`, `clean` (prompt_clean's output),
  `input_ids` and `attention_mask` ({L} each: the tokenizer with padding="max_length", truncation=True);
  `clean_cases`: 300 [text, prompt_clean(text)] pairs of random strings made of `CLEAN_PIECES`.
- text.npz `embeddings` [cases, {L}, {D}]: the prompt embeddings (hidden states of the real tokens, zeros after);
  `negative_default` [{L}, {D}]: the negative embedding encode_prompt makes when none is given (the empty prompt).
"""


def c4g_reference_readme(cfg: RefinerConfig, seed: int, inputs: dict) -> str:
    k, r = cfg.keyframes, cfg.rendered_latent_frames
    lat = f"[1, 16, {cfg.latent_frames}, {cfg.latent_height}, {cfg.latent_width}]"
    n = inputs["rendered"].shape[0]
    return f"""# Reference outputs of C4G's refinement layout (PyTorch, CPU, float32)

Made by `python -m c4g.wan.export --tiny --layout c4g` (c4g/wan/c4g_layout.py), seed {seed}, with diffusers'
modules holding the same random weights as the ONNX graphs (float64 RoPE tables; the graphs use float32 ones).
The layout: {k} keyframes, each VAE-encoded alone, then the {n} rendered frames padded to {cfg.frames} (the last
repeated) and encoded as one chunk: {k} + {r} latent frames, latents {lat}. Temporal RoPE positions: keyframe
source index + 500, then 0..{r - 1}. DiffSynth's Euler ("Wan" schedule: linspace(1, 0, steps + 1)[:-1], shifted),
{cfg.steps} steps, shift {cfg.shift}, guidance {cfg.guidance_scale}.

## pipeline_c4g.npz
- inputs: `keyframes` [{k}, {cfg.height}, {cfg.width}, 3] and `rendered` [{n}, {cfg.height}, {cfg.width}, 3] in [0, 1] (multiples of
  1/255); `keyframe_indices` [{k}] (int64, source-frame indices); `prompt_embeds`, `negative_prompt_embeds` [1, {cfg.text_tokens},
  {cfg.transformer['text_dim']}]; `noise` {lat}.
- `rendered_padded` [{cfg.frames}, H, W, 3]; `positions` [{cfg.latent_frames}] (int64).
- `control` [1, 96, {cfg.latent_frames}, h, w]: [inactive 16 ; reactive 16 ; mask 64], keyframe slots first.
- `sigmas` [steps + 1], `timesteps` [steps]: the schedule (timesteps sigma * 1000, f32, not rounded).
- `velocity_first`: the conditional velocity of step 0; `step_latents`, `step_velocity_cond`, `step_velocity_uncond`
  [steps, ...{lat}]: what each step saw and the two transformer outputs (guided = uncond + g (cond - uncond)).
- `latents_final` {lat}; `decoder_input` [1, 16, {r}, h, w]: the rendered part, un-normalised;
  `frames_out` [{n}, H, W, 3]: the refined frames (decoded chunk / 2 + 0.5, clamped, first {n}).

## transformer_positions.npz
Random `latents`, `timestep`, `text_embeddings`, `control`, `control_scale` and `positions` (keyframes at 500, 503, 509)
→ `velocity` (the positioned transformer graph's check).

## vae_frame.npz
`frame` [1, 3, 1, H, W] uniform in [-1, 1] → `latents_mode` [1, 16, 1, h, w] (the one-frame encoder graph's check).
"""


# ----------------------------------------------------------------------------- CLI


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--tiny", action="store_true", help="the tiny random-weight fixture with LoRA files and reference outputs")
    which.add_argument("--diffusers", metavar="DIR", help="a diffusers checkout of Wan2.1-VACE (transformer/, vae/, scheduler/)")
    which.add_argument("--random-init", action="store_true", help="random weights at --config's size")
    parser.add_argument("--config", choices=sorted(PRESETS), default="1.3b", help="architecture for --random-init")
    parser.add_argument("--layout", choices=["vace", "c4g"], default="vace", help="VACE's sequence, or C4G's keyframes + rendered frames (c4g_layout.py)")
    parser.add_argument("--keyframes", type=int, default=12, help="keyframe slots of the c4g layout (C4G trained with 12)")
    parser.add_argument("--out", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--name")
    parser.add_argument("--frames", type=int, help="video frames (4k + 1; the rendered frames in the c4g layout); default 81")
    parser.add_argument("--height", type=int, help="multiple of 16; default 480")
    parser.add_argument("--width", type=int, help="multiple of 16; default 832")
    parser.add_argument("--text-tokens", type=int, help="text embedding length; default 512")
    parser.add_argument("--fp16", action="store_true", help="f16 transformer weights (inputs / outputs stay f32)")
    parser.add_argument("--lora", metavar="FILE", help="merge this LoRA (.safetensors, PEFT or Wan naming) into the transformer's f32 weights before --fp16 rounds them (lora.merge_into_transformer)")
    parser.add_argument("--lora-scale", type=float, default=1.0, help="the merged LoRA's strength (times its own alpha / r)")
    parser.add_argument("--attention", choices=["fused", "plain"], default="fused")
    parser.add_argument("--external-data", action="store_true", help="weights in .onnx.data even under 2 GB")
    parser.add_argument("--device", default="cpu", help="where to trace (cuda is much faster at real sizes)")
    parser.add_argument("--text-encoder", action="store_true", help="also export umT5's encoder (~23 GB in f32) and tokenizer, so workers take captions")
    args = parser.parse_args(argv)
    if args.tiny and args.lora:
        parser.error("--tiny makes its own LoRA files (lora/); --lora merges one into --diffusers or --random-init weights")
    if args.tiny and args.layout == "c4g":
        meta = export_tiny_c4g(Path(args.out), args.seed, args.attention)
    elif args.tiny:
        meta = export_tiny(Path(args.out), args.seed, args.attention)
    else:
        meta = export_real(args)
    print(json.dumps({"name": meta["name"], "out": args.out, "files": meta["files"], "parameters": meta["parameters"]}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
