"""LoRA files for the refiner in both conventions, and the module-name map between them.

Two files hold the same low-rank deltas:

- PEFT / diffusers (`lora/peft/adapter_model.safetensors` + `adapter_config.json`):
  `transformer.<diffusers module>.lora_A.weight` [r, in] and `.lora_B.weight` [out, r]; the scale
  lora_alpha / r comes from adapter_config.json (a copy sits in the safetensors header under
  `lora_adapter_metadata`, as `transformer.r` / `transformer.lora_alpha` / ..., which is where diffusers'
  `load_lora_weights` reads it: without it diffusers assumes alpha = r).
- Original Wan / ComfyUI (`lora/wan/lora.safetensors`):
  `diffusion_model.<wan module>.lora_down.weight` [r, in], `.lora_up.weight` [out, r] and `.alpha`
  (a 0-d f32 tensor); scale alpha / r (r = lora_down's first dim).

Merge (both): W[out, in] += scale * lora_B @ lora_A, with W the ONNX initializer
`<diffusers module>.weight` (diffusers' parameter name, [out, in]).

`lora/name_map.json` lists, for every module the tiny LoRA targets, the Wan module name, the diffusers
module name and the ONNX initializer name (and its shape), plus the substitution rules that map any Wan
module name onto diffusers' (the same table diffusers' own checkpoint converter uses). diffusers'
`load_lora_weights` converts Wan-named LoRAs for the main blocks only: a key under `vace_blocks` makes it
raise (its converter knows no VACE names), so a Wan-named VACE LoRA has to be mapped by us.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

PEFT_PREFIX = "transformer."
WAN_PREFIX = "diffusion_model."

# Wan module name → diffusers module name: regular expressions (no groups) replaced by literal text, in
# order. Written without backreferences so that any regex engine (Rust's `regex` too) applies them as is.
WAN_TO_DIFFUSERS_RULES: list[tuple[str, str]] = [
    (r"^time_embedding\.0$", "condition_embedder.time_embedder.linear_1"),
    (r"^time_embedding\.2$", "condition_embedder.time_embedder.linear_2"),
    (r"^text_embedding\.0$", "condition_embedder.text_embedder.linear_1"),
    (r"^text_embedding\.2$", "condition_embedder.text_embedder.linear_2"),
    (r"^time_projection\.1$", "condition_embedder.time_proj"),
    (r"^head\.head$", "proj_out"),
    *[(rf"\.{wan}\.{p}$", f".{ours}.{q}") for wan, ours in (("self_attn", "attn1"), ("cross_attn", "attn2"))
      for p, q in (("q", "to_q"), ("k", "to_k"), ("v", "to_v"), ("o", "to_out.0"))],
    (r"\.ffn\.0$", ".ffn.net.0.proj"),
    (r"\.ffn\.2$", ".ffn.net.2"),
    (r"\.before_proj$", ".proj_in"),
    (r"\.after_proj$", ".proj_out"),
]


def wan_to_diffusers(name: str) -> str:
    """`blocks.3.self_attn.q` → `blocks.3.attn1.to_q`; `vace_blocks.0.before_proj` → `vace_blocks.0.proj_in`."""
    for pattern, repl in WAN_TO_DIFFUSERS_RULES:
        name = re.sub(pattern, lambda _, r=repl: r, name)
    return name


_DIFFUSERS_TO_WAN = [
    (r"^condition_embedder\.time_embedder\.linear_1$", "time_embedding.0"),
    (r"^condition_embedder\.time_embedder\.linear_2$", "time_embedding.2"),
    (r"^condition_embedder\.text_embedder\.linear_1$", "text_embedding.0"),
    (r"^condition_embedder\.text_embedder\.linear_2$", "text_embedding.2"),
    (r"^condition_embedder\.time_proj$", "time_projection.1"),
    (r"^proj_out$", "head.head"),
    (r"\.attn1\.", ".self_attn."),
    (r"\.attn2\.", ".cross_attn."),
    (r"\.to_q$", ".q"),
    (r"\.to_k$", ".k"),
    (r"\.to_v$", ".v"),
    (r"\.to_out\.0$", ".o"),
    (r"\.ffn\.net\.0\.proj$", ".ffn.0"),
    (r"\.ffn\.net\.2$", ".ffn.2"),
    (r"^(vace_blocks\.\d+)\.proj_in$", r"\1.before_proj"),
    (r"^(vace_blocks\.\d+)\.proj_out$", r"\1.after_proj"),
]


def diffusers_to_wan(name: str) -> str:
    for pattern, repl in _DIFFUSERS_TO_WAN:
        name = re.sub(pattern, repl, name)
    return name


def tiny_targets(transformer_config) -> list[str]:
    """The diffusers modules the tiny LoRA adapts: every linear of every main block (self- and
    cross-attention q / k / v / o, both FFN layers), and in the VACE branch proj_in, each proj_out, and a
    few attention / FFN linears."""
    targets = []
    for i in range(transformer_config["num_layers"]):
        for attn in ("attn1", "attn2"):
            targets += [f"blocks.{i}.{attn}.{p}" for p in ("to_q", "to_k", "to_v", "to_out.0")]
        targets += [f"blocks.{i}.ffn.net.0.proj", f"blocks.{i}.ffn.net.2"]
    targets.append("vace_blocks.0.proj_in")
    for j in range(len(transformer_config["vace_layers"])):
        targets += [f"vace_blocks.{j}.attn1.to_q", f"vace_blocks.{j}.attn2.to_v", f"vace_blocks.{j}.ffn.net.0.proj", f"vace_blocks.{j}.proj_out"]
    return targets


def random_lora(transformer: torch.nn.Module, targets: list[str], rank: int, alpha: float, seed: int) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """{diffusers module: (A [r, in], B [out, r])}, sized so that scale * B @ A is about as large as the
    module's own weight (the outputs change visibly)."""
    gen = torch.Generator().manual_seed(seed)
    modules = dict(transformer.named_modules())
    scale = alpha / rank
    out = {}
    for name in targets:
        w = modules[name].weight.detach()
        n_out, n_in = w.shape
        a = torch.randn(rank, n_in, generator=gen) / n_in**0.5
        b = torch.randn(n_out, rank, generator=gen) * (0.5 * float(w.std()) * n_in**0.5 / rank**0.5 / scale)
        out[name] = (a.contiguous(), b.contiguous())
    return out


def adapter_config(targets: list[str], rank: int, alpha: float) -> dict:
    return {
        "peft_type": "LORA",
        "r": rank,
        "lora_alpha": alpha,
        "target_modules": sorted(targets),
        "lora_dropout": 0.0,
        "bias": "none",
        "use_rslora": False,
        "use_dora": False,
        "init_lora_weights": True,
    }


def write_lora_files(lora: dict, rank: int, alpha: float, out: Path, weight_shapes: dict[str, list[int]]) -> dict:
    """Write lora/peft/, lora/wan/ and lora/name_map.json under `out`; return the name map."""
    peft_dir, wan_dir = out / "peft", out / "wan"
    peft_dir.mkdir(parents=True, exist_ok=True)
    wan_dir.mkdir(parents=True, exist_ok=True)
    targets = sorted(lora)
    config = adapter_config(targets, rank, alpha)
    peft_tensors, wan_tensors = {}, {}
    for name in targets:
        a, b = lora[name]
        peft_tensors[f"{PEFT_PREFIX}{name}.lora_A.weight"] = a
        peft_tensors[f"{PEFT_PREFIX}{name}.lora_B.weight"] = b
        wan = diffusers_to_wan(name)
        assert wan_to_diffusers(wan) == name, (name, wan)
        wan_tensors[f"{WAN_PREFIX}{wan}.lora_down.weight"] = a
        wan_tensors[f"{WAN_PREFIX}{wan}.lora_up.weight"] = b
        wan_tensors[f"{WAN_PREFIX}{wan}.alpha"] = torch.tensor(float(alpha))
    diffusers_meta = {f"transformer.{k}": v for k, v in config.items() if k != "peft_type"}
    # One header entry only: safetensors writes its metadata map in no fixed order, and the file should be
    # byte-for-byte reproducible.
    metadata = {"lora_adapter_metadata": json.dumps(diffusers_meta, indent=2, sort_keys=True)}
    save_file(peft_tensors, str(peft_dir / "adapter_model.safetensors"), metadata=metadata)
    (peft_dir / "adapter_config.json").write_text(json.dumps(config, indent=2) + "\n")
    save_file(wan_tensors, str(wan_dir / "lora.safetensors"), metadata={"format": "pt"})
    name_map = {
        "format": "c4g-lora-name-map",
        "format_version": 1,
        "rank": rank,
        "alpha": alpha,
        "scale": alpha / rank,
        "prefixes": {"wan": WAN_PREFIX, "peft": PEFT_PREFIX},
        "suffixes": {
            "wan": {"down": ".lora_down.weight", "up": ".lora_up.weight", "alpha": ".alpha"},
            "peft": {"down": ".lora_A.weight", "up": ".lora_B.weight"},
        },
        "merge": "W[out, in] += (alpha / rank) * up[out, r] @ down[r, in]",
        "modules": [
            {"wan": diffusers_to_wan(name), "diffusers": name, "onnx_initializer": f"{name}.weight", "shape": weight_shapes[name]}
            for name in targets
        ],
        "rules": {
            "how": "Wan module name -> diffusers module name: for each rule in order, replace matches of the regex `pattern` by the literal `replacement`",
            "list": [{"pattern": p, "replacement": r} for p, r in WAN_TO_DIFFUSERS_RULES],
        },
    }
    (out / "name_map.json").write_text(json.dumps(name_map, indent=2) + "\n")
    return name_map


def deltas_from_peft(path: Path, config: dict) -> dict[str, torch.Tensor]:
    """{ONNX initializer name: scale * B @ A} from a PEFT file (scale lora_alpha / r, or / sqrt(r) for rsLoRA)."""
    return dict(iter_deltas_peft(path, config))


def iter_deltas_peft(path: Path, config: dict):
    """`deltas_from_peft`, one (name, delta) at a time (float64: at the 1.3B size all of them are 11 GB)."""
    tensors = load_file(str(path))
    r, alpha = config["r"], config["lora_alpha"]
    scale = alpha / (r**0.5 if config.get("use_rslora") else r)
    for key, a in tensors.items():
        if key.endswith(".lora_A.weight"):
            module = key.removeprefix(PEFT_PREFIX).removesuffix(".lora_A.weight")
            b = tensors[key.replace(".lora_A.", ".lora_B.")]
            yield f"{module}.weight", scale * (b.double() @ a.double())


def deltas_from_wan(path: Path) -> dict[str, torch.Tensor]:
    """{ONNX initializer name: alpha / r * up @ down} from a Wan-named file (alpha = r when absent)."""
    return dict(iter_deltas_wan(path))


def iter_deltas_wan(path: Path):
    """`deltas_from_wan`, one (name, delta) at a time."""
    tensors = load_file(str(path))
    for key, down in tensors.items():
        if key.endswith(".lora_down.weight"):
            module = key.removeprefix(WAN_PREFIX).removesuffix(".lora_down.weight")
            up = tensors[key.replace(".lora_down.", ".lora_up.")]
            rank = down.shape[0]
            alpha_key = key.replace(".lora_down.weight", ".alpha")
            alpha = float(tensors[alpha_key]) if alpha_key in tensors else float(rank)
            yield f"{wan_to_diffusers(module)}.weight", alpha / rank * (up.double() @ down.double())


def merge_into_transformer(transformer: torch.nn.Module, path: Path, scale: float = 1.0) -> dict:
    """Add `scale` x a LoRA's deltas (either naming) to `transformer`'s weights in place, in float64
    then rounded once to each weight's own type; returns refiner.json's `lora_merged` entry.

    This is the export-time merge (`python -m c4g.wan.export --lora`): done on the f32 weights
    before `--fp16` rounds them, it rounds each merged weight once, where merging into an f16
    package at load rounds the base weights and then the sum. A PEFT file takes r and lora_alpha
    from the `adapter_config.json` beside it; a Wan-named file its own `.alpha` (r when absent).
    Every delta must land on a parameter of the same shape, or this fails naming it."""
    path = Path(path)
    if path.is_dir():
        path = path / "adapter_model.safetensors"
    with safe_open(str(path), "pt") as f:
        keys, header = list(f.keys()), f.metadata() or {}
    if any(k.endswith(".lora_A.weight") for k in keys):
        config_path = path.parent / "adapter_config.json"
        if config_path.exists():
            config = json.loads(config_path.read_text())
        elif "lora_adapter_metadata" in header:  # diffusers' save_lora_weights: keys `transformer.r`, ...
            config = {k.removeprefix("transformer."): v for k, v in json.loads(header["lora_adapter_metadata"]).items()}
        else:
            raise ValueError(f"{path}: a PEFT LoRA needs its adapter_config.json beside it, or the config in its header (r, lora_alpha)")
        deltas = iter_deltas_peft(path, config)
        naming = "peft"
    elif any(k.endswith(".lora_down.weight") for k in keys):
        deltas = iter_deltas_wan(path)
        naming = "wan"
    else:
        raise ValueError(f"{path}: no LoRA factors (`.lora_A.weight` / `.lora_down.weight` keys)")
    params = dict(transformer.named_parameters())
    modules = 0
    for name, delta in deltas:
        modules += 1
        p = params.get(name)
        if p is None:
            raise ValueError(f"{path}: LoRA module {name.removesuffix('.weight')!r} is not a weight of the transformer")
        if tuple(p.shape) != tuple(delta.shape):
            raise ValueError(f"{path}: LoRA module {name.removesuffix('.weight')!r} gives {list(delta.shape)} for a weight of {list(p.shape)}")
        with torch.no_grad():
            p.copy_((p.double() + scale * delta).to(p.dtype))
    return {
        "file": path.name,
        "sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
        "naming": naming,
        "scale": scale,
        "modules": modules,
    }
