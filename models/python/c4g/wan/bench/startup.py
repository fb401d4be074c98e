"""Start-up benchmark of the refiner worker: seconds from starting `c4g-refiner` to its "worker
started" line (package read, LoRA merged, sessions created) and its resident memory, with and
without a LoRA over every linear of the main blocks (random factors; only the shapes matter).

    cargo build --release -p c4g-refiner
    python -m c4g.wan.bench.startup --package /tmp/wan13b --binary ../../target/release/c4g-refiner
    # two builds in one sitting (e.g. before and after a change), and a second package:
    python -m c4g.wan.bench.startup --package /tmp/wan13b --package /tmp/wan13b-f16 \
        --binary before=/tmp/c4g-refiner-before --binary after=../../target/release/c4g-refiner

A package is any refiner package (e.g. `python -m c4g.wan.export --random-init --config 1.3b ...`);
its `refiner.json` gives the transformer config the LoRA is shaped for. `--write-lora DIR` only
writes the LoRA (to merge it at export: `python -m c4g.wan.export ... --lora DIR/adapter_model.safetensors`).
Resident memory is split into anonymous memory and mapped files (ONNX Runtime maps aligned external
data): the kernel can drop mapped file pages under pressure, not anonymous ones. Numbers go with the
machine into docs/benchmarks.md.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch
from safetensors.torch import save_file

from c4g.wan.configs import build_transformer


def write_lora(package: Path, out: Path, rank: int, seed: int = 0) -> int:
    """A PEFT LoRA (alpha = rank) over every Linear of the main blocks' attention and FFN; returns
    its parameter count."""
    cfg = json.loads((package / "refiner.json").read_text())["diffusers_config"]["transformer"]
    model = build_transformer(cfg, device="meta")
    gen = torch.Generator().manual_seed(seed)
    targets, tensors = [], {}
    for name, module in model.named_modules():
        if isinstance(module, torch.nn.Linear) and name.startswith("blocks.") and (".attn" in name or ".ffn." in name):
            out_features, in_features = module.weight.shape
            targets.append(name)
            tensors[f"transformer.{name}.lora_A.weight"] = torch.randn(rank, in_features, generator=gen) * 0.01
            tensors[f"transformer.{name}.lora_B.weight"] = torch.randn(out_features, rank, generator=gen) * 0.01
    save_file(tensors, str(out / "adapter_model.safetensors"))
    config = {"peft_type": "LORA", "r": rank, "lora_alpha": float(rank), "target_modules": sorted(targets)}
    (out / "adapter_config.json").write_text(json.dumps(config))
    return sum(t.numel() for t in tensors.values())


def _status(pid: int, key: str) -> str:
    line = next(l for l in Path(f"/proc/{pid}/status").read_text().splitlines() if l.startswith(key + ":"))
    return f"{int(line.split()[1]) / 1e6:.1f} GB"


def time_startup(binary: str, package: Path, extra: list[str]) -> str:
    """One start: seconds to ready, peak resident memory, and resident memory 5 s after ready."""
    start = time.monotonic()
    proc = subprocess.Popen(
        [binary, "--server", "http://127.0.0.1:9", "--package", str(package), *extra],
        stderr=subprocess.PIPE, text=True, env=dict(os.environ, RUST_LOG="info"),
    )
    assert proc.stderr is not None
    for line in proc.stderr:
        if "worker started" in line:
            break
    else:
        raise RuntimeError(f"c4g-refiner exited with {proc.wait()} before it was ready")
    elapsed = time.monotonic() - start
    peak = _status(proc.pid, "VmHWM")
    time.sleep(5)
    settled = ", ".join(f"{key} {_status(proc.pid, key)}" for key in ("VmRSS", "RssAnon", "RssFile"))
    proc.kill()
    proc.wait()
    return f"{elapsed:.1f} s to ready, peak {peak}; once ready {settled}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--package", type=Path, action="append", help="a refiner package (repeatable)")
    parser.add_argument("--binary", action="append", help="c4g-refiner, or LABEL=PATH (repeatable: started in turns)")
    parser.add_argument("--rank", type=int, default=128)
    parser.add_argument("--runs", type=int, default=2)
    parser.add_argument("--write-lora", type=Path, metavar="DIR", help="only write the LoRA for the first --package into DIR")
    args = parser.parse_args(argv)
    if not args.package:
        parser.error("--package is required")
    if args.write_lora:
        args.write_lora.mkdir(parents=True, exist_ok=True)
        print(f"LoRA: rank {args.rank}, {write_lora(args.package[0], args.write_lora, args.rank)} parameters in {args.write_lora}")
        return 0
    if not args.binary:
        parser.error("--binary is required")
    binaries = [b.split("=", 1) if "=" in b else [b, b] for b in args.binary]
    with tempfile.TemporaryDirectory() as tmp:
        params = write_lora(args.package[0], Path(tmp), args.rank)
        print(f"LoRA: rank {args.rank}, {params} parameters", flush=True)
        for _ in range(args.runs):
            for package in args.package:
                for label, binary in binaries:
                    for what, extra in (("no LoRA", []), ("LoRA merged", ["--lora", str(Path(tmp) / "adapter_model.safetensors")])):
                        print(f"{package.name} · {label} · {what}: {time_startup(binary, package, extra)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
