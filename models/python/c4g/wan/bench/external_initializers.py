"""What ONNX Runtime holds for weights given as external initializers, by layout: the question
behind the refiner's doubled memory with a merged LoRA (docs/benchmarks.md, "Refiner").

    python -m c4g.wan.bench.external_initializers [--layers 8] [--side 4096]

Builds a chain of MatMuls over `--layers` float32 weights of `--side`² (64 MiB each at 4096),
stored either as the exporter writes linears ([out, in] behind a Transpose) or [in, out] used
directly, and creates a CPU session for each way: weights read from the model's external-data
file, or handed in as external initializers (`SessionOptions.add_external_initializers`, what the
refiner does with merged weights; then the file's own data is deleted first, so it cannot be
what is read), each with prepacking on and off (`session.disable_prepacking`). Prints how much
resident memory creating the session and running it once added, against the weights' size; each
way runs in its own process so that freed memory does not blur the next.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np


def resident_mib() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS"):
            return int(line.split()[1]) // 1024
    return 0


def one_way(layout: str, given: str, prepack: bool, layers: int, side: int) -> None:
    import onnx
    import onnxruntime as ort
    from onnx import TensorProto, helper, numpy_helper

    with tempfile.TemporaryDirectory() as tmp:
        nodes, initializers, weights, x = [], [], [], "x"
        for i in range(layers):
            w = (np.random.default_rng(i).standard_normal((side, side)) * 0.01).astype(np.float32)
            name = f"w{i}"
            if layout == "transposed":
                nodes.append(helper.make_node("Transpose", [name], [f"t{i}"], perm=[1, 0]))
                nodes.append(helper.make_node("MatMul", [x, f"t{i}"], [f"y{i}"]))
            else:
                w = np.ascontiguousarray(w.T)
                nodes.append(helper.make_node("MatMul", [x, name], [f"y{i}"]))
            initializers.append(numpy_helper.from_array(w, name))
            weights.append((name, w))
            x = f"y{i}"
        graph = helper.make_graph(
            nodes, "chain", [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, side])],
            [helper.make_tensor_value_info(x, TensorProto.FLOAT, [1, side])], initializers,
        )  # fmt: skip
        model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 18)])
        model.ir_version = 10
        path = Path(tmp) / "m.onnx"
        onnx.save(model, str(path), save_as_external_data=True, location="m.data", size_threshold=0)
        del model, graph, initializers
        options = ort.SessionOptions()
        options.enable_cpu_mem_arena = False
        if not prepack:
            options.add_session_config_entry("session.disable_prepacking", "1")
        held = []
        if given == "external initializers":
            held = [ort.OrtValue.ortvalue_from_numpy(w) for _, w in weights]
            options.add_external_initializers([n for n, _ in weights], held)
            os.remove(Path(tmp) / "m.data")
        else:
            weights.clear()
        before = resident_mib()
        session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        session.run(None, {"x": np.ones((1, side), np.float32)})
        added = resident_mib() - before
        size = layers * side * side * 4 >> 20
        print(f"| {layout} | {given} | {'on' if prepack else 'off'} | {added} | {size} |", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m c4g.wan.bench.external_initializers", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--layers", type=int, default=8)
    ap.add_argument("--side", type=int, default=4096)
    ap.add_argument("--one", nargs=3, metavar=("LAYOUT", "GIVEN", "PREPACK"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        layout, given, prepack = args.one
        one_way(layout, given.replace("_", " "), prepack == "on", args.layers, args.side)
        return 0
    print("| layout | weights | prepacking | MiB the session added | MiB of weights |")
    print("|---|---|---|---|---|")
    for layout in ("transposed", "direct"):
        for given in ("file", "external_initializers"):
            for prepack in ("on", "off"):
                subprocess.run(
                    [sys.executable, "-m", "c4g.wan.bench.external_initializers", "--layers", str(args.layers),
                     "--side", str(args.side), "--one", layout, given, prepack],
                    check=True,
                )  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
