"""A package's weights back in the official checkpoint layout: the export tool run backwards.

    python -m c4g.package.to_checkpoint --package models/c4g-tiny --config runs/c4g-tiny/config.json --out c4g-tiny.ckpt

Why: a served package is all a user may have of a model (c4g-tiny's training run is not
committed, only its package), and fine-tuning one (c4g-tiny v2 starts from v1) needs its weights
in the mirror. The ONNX graphs hold every parameter, but the exporter names only those it keeps
as they are; the matrices of MatMuls become anonymous, transposed constants (`onnx::MatMul_N`),
and the export's precomputed tables (the resized positional embedding, RoPE, the time
frequencies) are not parameters.

How: the same configuration is exported again with random weights, each parameter's values
unique, through the same `export_package`; torch names a graph's constants deterministically
for a given model, so each initializer name there is matched to the parameter whose values it
holds (as it is, or transposed). The package's initializers of those names are then the
parameters. Parameters that only feed precomputed tables must appear elsewhere as themselves or
the tool stops; nothing is guessed. The result is checked by `verify`: the mirror with the
recovered weights against the package's own graphs on ONNX Runtime.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch
from onnx import numpy_helper

from c4g.model.config import C4GConfig
from c4g.model.decoder import to_canonical
from c4g.model.network import C4G

from .export import export_package

GRAPHS = ("encoder", "decoder", "feature_decoder")
# Parameters that no exported graph reads: the DINOv2 mask token, which only masked training uses.
# They come back as the architecture initialises them.
UNUSED = {"backbone.aggregator.patch_embed.mask_token"}


def _initializers(path: Path) -> tuple[dict[str, np.ndarray], dict[tuple[str, int], str]]:
    """A graph's constants by name, and by where they are used: (consuming node's name, input slot)."""
    graph = onnx.load(str(path)).graph
    values = {i.name: numpy_helper.to_array(i) for i in graph.initializer}
    uses = {(n.name, k): x for n in graph.node for k, x in enumerate(n.input) if x in values}
    return values, uses


def _graph_paths(package: Path) -> dict[str, Path]:
    files = json.loads((package / "model.json").read_text())["files"]
    return {g: package / files[g] for g in GRAPHS if g in files}


def _probe(cfg: C4GConfig, form: str) -> tuple[C4G, dict[str, tuple]]:
    """A model of `cfg` whose parameters' elements all hold distinct values, and its export's
    constants. The values are distinct float32 numbers from 1 up (consecutive bit patterns, in a
    random order, so no arithmetic of the export's precomputed tables lands on a run of them)."""
    model = C4G(cfg).eval()
    count = sum(p.numel() for p in model.parameters())
    if count >= 2**29:
        raise ValueError(f"{count} parameters: too many for distinct probe values")
    bits = np.random.default_rng(0).permutation(count).astype(np.uint32) + np.uint32(0x3F800000)
    values = torch.from_numpy(bits.view(np.float32))
    with torch.no_grad():
        offset = 0
        for p in model.parameters():
            p.copy_(values[offset : offset + p.numel()].view(p.shape))
            offset += p.numel()
    with tempfile.TemporaryDirectory() as tmp:
        export_package(model, Path(tmp), "probe", "0", {"kind": "probe"}, decoder_form=form)
        return model, {g: _initializers(p) for g, p in _graph_paths(Path(tmp)).items()}


# A run of a constant's elements taken for consecutive elements of one parameter must be this
# long (or the whole constant), so that no stray equality places a value.
SHORTEST_RUN = 16


def _place(value: np.ndarray, params: dict[str, np.ndarray], index: dict[float, tuple[str, int]]) -> list[tuple] | None:
    """Where a probe constant's values sit in the parameters, as pieces (parameter, transposed,
    offset, constant's flat start, length): a parameter's transposed matrix or a block of its
    columns (a MatMul's matrix, or the export's slice of a fused projection such as the last
    layer's q), else runs of consecutive elements (a parameter as it is or reshaped, and
    concatenations of slices, such as the aggregator's camera and register tokens). `index` maps
    each probe value to its parameter and flat position."""
    if value.dtype != np.float32 or value.size == 0:
        return None
    if value.ndim == 2:
        for name, p in params.items():
            if p.ndim == 2 and value.shape[0] == p.shape[1] and value.shape[1] <= p.shape[0] and value.shape != p.shape:
                for j in np.flatnonzero(p[:, 0] == value[0, 0]):
                    if np.array_equal(p[j : j + value.shape[1]].T, value):
                        return [(name, True, int(j), 0, value.size)]
            if p.ndim == 2 and p.T.shape == value.shape and np.array_equal(p.T, value):
                return [(name, True, 0, 0, value.size)]
    flat, pieces, i = value.ravel(), [], 0
    while i < flat.size:
        hit = index.get(float(flat[i]))
        if hit is None:
            return None
        name, start = hit
        source = params[name].ravel()
        k = 1
        while i + k < flat.size and start + k < source.size and flat[i + k] == source[start + k]:
            k += 1
        if k < min(SHORTEST_RUN, flat.size):
            return None
        pieces.append((name, False, start, i, k))
        i += k
    return pieces


def _scope_parameter(node: str) -> str:
    """The weight of the module a MatMul node was exported from: torch names nodes by module scope
    (`/gmae_decoder/layers.0.1/net/net.1/MatMul` is `gmae_decoder.layers.0.1.net.1`)."""
    parts: list[str] = []
    for segment in node.strip("/").split("/")[:-1]:
        if parts and segment.startswith(parts[-1] + "."):
            parts[-1] = segment
        else:
            parts.append(segment)
    return ".".join(parts) + ".weight"


def recover(package: Path, cfg: C4GConfig) -> dict[str, torch.Tensor]:
    """The state (parameters and buffers) of the model in `package`, whose architecture is `cfg`.

    Each package constant is matched to the probe's constant used at the same place (node and
    input slot), or else the one of the same name (exporters number anonymous constants per
    export, so a package made before a change to its graph's code holds other numbers); a MatMul
    matrix that the probe's graph has no place for is its module's weight, transposed. Parameters must be covered completely, and copies must agree."""
    manifest = json.loads((package / "model.json").read_text())
    if "context_projection" in manifest["files"]:
        # The precomputed form folds the first decoder layer's norm into its projection: only the
        # product is in the package, and the architecture has no bias to hold the folded shift.
        raise ValueError("a package in the precomputed decoder form holds the first decoder layer's norm folded into its projection, which cannot be taken apart; export the model in the plain form (--decoder-form plain)")
    model, probe = _probe(cfg, "plain")
    params = {n: p.detach().numpy() for n, p in model.named_parameters()}
    recovered = {n: np.full(p.shape, np.nan, np.float64) for n, p in params.items()}

    index = {float(v): (n, i) for n, p in params.items() for i, v in enumerate(p.ravel())}

    def put(pieces: list[tuple], value: np.ndarray) -> None:
        for name, transposed, offset, start, length in pieces:
            if transposed:
                block = value.T
                target = recovered[name][offset : offset + len(block)]
            else:
                block = value.ravel()[start : start + length]
                target = recovered[name].reshape(-1)[offset : offset + length]
            if not np.all(np.isnan(target) | (target == block)):
                raise ValueError(f"{name}: two copies in the package disagree")
            target[...] = block

    for graph, path in _graph_paths(package).items():
        actual, actual_uses = _initializers(path)
        probe_values, probe_uses = probe[graph]
        for use, name in actual_uses.items():
            # The place first: anonymous constants (`onnx::MatMul_N`) are numbered per export, and
            # a change anywhere in a graph renumbers them, so a name can stand for another matrix
            # of the same shape; a node's scope names the module it came from.
            twin = probe_uses.get(use) or (name if name in probe_values else None)
            placed = _place(probe_values[twin], params, index) if twin is not None and probe_values[twin].shape == actual[name].shape else None
            if placed is not None:
                put(placed, actual[name])
            elif use[1] == 1 and use[0].endswith("/MatMul") and _scope_parameter(use[0]) in params:
                weight = _scope_parameter(use[0])
                if params[weight].T.shape != actual[name].shape:
                    raise ValueError(f"{path}: {name} at {use[0]} is not {weight}'s shape transposed")
                put([(weight, True, 0, 0, actual[name].size)], actual[name])
    missing = sorted(n for n, v in recovered.items() if n not in UNUSED and np.isnan(v).any())
    if missing:
        raise ValueError(f"{len(missing)} parameters appear in no graph as themselves: {', '.join(missing[:8])}")
    initial = C4G(cfg).state_dict()
    state = {n: initial[n].clone() if n in UNUSED else torch.from_numpy(v.astype(np.float32)) for n, v in recovered.items()}
    # Buffers (the anchor positions, the time frequencies) follow from the configuration; the
    # graphs hold them under their own names, and those are taken where present.
    named = {}
    for path in _graph_paths(package).values():
        named.update(_initializers(path)[0])
    for n, v in initial.items():
        if n not in state:
            held = named.get(f"model.{n}")
            state[n] = torch.from_numpy(held.copy()) if held is not None and held.shape == tuple(v.shape) else v.clone()
    return state


def verify(package: Path, model: C4G, seed: int = 0) -> float:
    """Largest difference between the mirror's Gaussians and the package's on random frames (ONNX
    Runtime, CPU)."""
    import onnxruntime as ort

    cfg = model.cfg
    paths = _graph_paths(package)
    rng = np.random.default_rng(seed)
    frames = rng.uniform(-1, 1, (3, 3, cfg.image_size, cfg.image_size)).astype(np.float32)
    ctx = np.array([[0.0, 0.5, 1.0]], np.float32)
    tgt = np.array([0.25], np.float32)
    enc = ort.InferenceSession(str(paths["encoder"]), providers=["CPUExecutionProvider"])
    feats = enc.run(None, {"frames": frames})[0]
    feeds = {"features": feats, "context_times": ctx, "target_times": tgt}
    dec = ort.InferenceSession(str(paths["decoder"]), providers=["CPUExecutionProvider"])
    names = {i.name for i in dec.get_inputs()}
    theirs = dec.run(None, {k: v for k, v in feeds.items() if k in names})[0]

    with torch.no_grad():
        f = model.encode(torch.from_numpy(frames))
        ours = to_canonical(model.decode(f, torch.from_numpy(ctx), torch.from_numpy(tgt))).numpy()
    return float(max(np.abs(f.numpy() - feats).max(), np.abs(ours - theirs).max()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.package.to_checkpoint", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--package", type=Path, required=True)
    ap.add_argument("--config", type=Path, help="the architecture as JSON (default: the package's model.json `architecture`)")
    ap.add_argument("--out", type=Path, required=True, help="checkpoint to write ({'state_dict': {'encoder.<name>': tensor}})")
    args = ap.parse_args(argv)
    manifest = json.loads((args.package / "model.json").read_text())
    cfg = C4GConfig.from_dict(json.loads(args.config.read_text()) if args.config else manifest["architecture"])
    try:
        state = recover(args.package, cfg)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    model = C4G(cfg).eval()
    model.load_state_dict(state)
    err = verify(args.package, model)
    print(f"recovered {len(state)} tensors; mirror vs package: largest difference {err:.2e}")
    if err > 1e-4:
        print("error: the recovered weights do not reproduce the package", file=sys.stderr)
        return 1
    torch.save({"state_dict": {f"encoder.{k}": v for k, v in state.items()}}, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
