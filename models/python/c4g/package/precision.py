"""Packages at lower precision: an f32 package converted to f16 or int8, for speed or memory.

    python -m c4g.package.precision --package models/c4g-tiny --precision int8 --out /tmp/c4g-tiny-int8
    python -m c4g.package.export ... --precision f16          # export, then convert in place

- **f16**: weights and activations in half precision (ONNX Runtime's float16 converter), with the
  graph inputs and outputs kept f32, so the engine feeds and reads the same tensors. ONNX Runtime's
  CPU kernels lack f16 for some operators; the converter then keeps those in f32 behind Casts, which
  makes an f16 package on a CPU mostly a memory saving (half the bytes), not a speed-up: measure
  before choosing it there. On CUDA f16 runs natively.
- **int8**: dynamic quantization of the large MatMuls (weights of at least `--min-elements`
  values: the attention projections and MLPs of every transformer block): int8 weights,
  activations quantized per run. The small MatMuls (time embedding MLP, the Gaussian head) stay f32:
  quantizing them costs most of the accuracy for little of the time.

Each converted graph carries its precision in the ONNX metadata entry `c4g.precision`, and
`model.json` declares the same value (`precision`, plus `precision_source`: what it was made from);
the engine refuses a package whose graphs and manifest disagree.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx

PRECISION_KEY = "c4g.precision"
PRECISIONS = ("f32", "f16", "int8")
# 128 x 128: every block matrix of c4g-tiny and of the official model, no time-MLP or head matrix.
DEFAULT_MIN_ELEMENTS = 16384
TWO_GB = 2**31


def _save(model: onnx.ModelProto, path: Path) -> None:
    """Save with the weights beside the graph only when protobuf's 2 GB limit requires it."""
    for stale in path.parent.glob(path.name + ".data"):
        stale.unlink()
    if model.ByteSize() >= TWO_GB - (64 << 20):
        onnx.save_model(model, str(path), save_as_external_data=True, all_tensors_to_one_file=True, location=path.name + ".data", size_threshold=1024)
    else:
        onnx.save_model(model, str(path))


def _stamp(model: onnx.ModelProto, precision: str) -> onnx.ModelProto:
    kept = [p for p in model.metadata_props if p.key != PRECISION_KEY]
    del model.metadata_props[:]
    model.metadata_props.extend(kept)
    model.metadata_props.add(key=PRECISION_KEY, value=precision)
    return model


def large_matmuls(model: onnx.ModelProto, min_elements: int) -> list[str]:
    """Names of the MatMul nodes whose constant weight holds at least `min_elements` values."""
    initializers = {i.name: i for i in model.graph.initializer}
    names = []
    for node in model.graph.node:
        if node.op_type != "MatMul":
            continue
        weights = [initializers[x] for x in node.input if x in initializers]
        if weights and int(np.prod(weights[0].dims)) >= min_elements:
            names.append(node.name)
    return names


def to_f16(src: Path, dst: Path) -> None:
    from onnxruntime.transformers.float16 import convert_float_to_float16

    model = onnx.load(str(src), load_external_data=True)
    large = model.ByteSize() >= TWO_GB - (64 << 20)
    converted = convert_float_to_float16(model, keep_io_types=True, disable_shape_infer=large)
    _save(_stamp(converted, "f16"), dst)


def to_int8(src: Path, dst: Path, min_elements: int) -> int:
    """Quantize `src`'s large MatMuls into `dst`; returns how many were quantized."""
    from onnxruntime.quantization import QuantType, quantize_dynamic

    model = onnx.load(str(src), load_external_data=False)
    chosen = set(large_matmuls(model, min_elements))
    others = [n.name for n in model.graph.node if n.op_type in ("MatMul", "Gemm") and n.name not in chosen]
    external = any(t.data_location == onnx.TensorProto.EXTERNAL for t in model.graph.initializer)
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / dst.name
        quantize_dynamic(
            str(src),
            str(raw),
            weight_type=QuantType.QInt8,
            op_types_to_quantize=["MatMul"],
            nodes_to_exclude=others,
            use_external_data_format=external,
            extra_options={"MatMulConstBOnly": True},
        )
        _save(_stamp(onnx.load(str(raw), load_external_data=True), "int8"), dst)
    return len(chosen)


def convert_package(src: Path, out: Path, precision: str, min_elements: int = DEFAULT_MIN_ELEMENTS) -> dict:
    """Write `src` (an f32 package) at `precision` into `out` (which may be `src` itself); returns
    the new manifest. Graphs are converted into a scratch folder first, so a failure leaves `out`
    as it was."""
    if precision not in PRECISIONS[1:]:
        raise ValueError(f"precision {precision!r} is not one of {PRECISIONS[1:]}")
    manifest = json.loads((src / "model.json").read_text())
    if manifest.get("precision", "f32") != "f32":
        raise ValueError(f"{src} is already {manifest['precision']}: convert from an f32 package")
    out.mkdir(parents=True, exist_ok=True)
    notes = {}
    with tempfile.TemporaryDirectory(dir=out) as tmp:
        staged = Path(tmp)
        for role, name in manifest["files"].items():
            if precision == "f16":
                to_f16(src / name, staged / name)
            else:
                notes[role] = f"{to_int8(src / name, staged / name, min_elements)} MatMuls in int8"
        for name in manifest["files"].values():
            # An f32 graph's external weights, when its converted graph holds them inline.
            if not (staged / (name + ".data")).exists():
                (out / (name + ".data")).unlink(missing_ok=True)
        for produced in staged.iterdir():
            target = out / produced.name
            target.unlink(missing_ok=True)
            shutil.move(str(produced), str(target))
            # Readable by every user (a container's server need not be the exporter).
            target.chmod(0o644)
    manifest["precision"] = precision
    manifest["precision_source"] = {
        "package": manifest.get("name"),
        "version": manifest.get("version"),
        "tool": "c4g.package.precision",
        **({"min_elements": min_elements, "quantized": notes} if precision == "int8" else {}),
    }
    (out / "model.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.package.precision", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--package", type=Path, required=True, help="an f32 package directory")
    ap.add_argument("--precision", choices=PRECISIONS[1:], required=True)
    ap.add_argument("--out", type=Path, required=True, help="where the converted package goes (may be --package)")
    ap.add_argument("--min-elements", type=int, default=DEFAULT_MIN_ELEMENTS, help="int8: smallest MatMul weight (values) to quantize")
    args = ap.parse_args(argv)
    try:
        manifest = convert_package(args.package, args.out, args.precision, args.min_elements)
    except (ValueError, FileNotFoundError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"wrote {args.out} ({manifest['precision']}; files: {', '.join(manifest['files'].values())})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
