"""How fast the client's C4GV reader turns a compact 4D stream into sets, on this machine.

    python clients/python/benches/c4gv_read.py STREAM.c4gv [...]
    python clients/python/benches/c4gv_read.py --server http://127.0.0.1:8080 --clip ID [--step 0.01]

Streams saved before (``POST /v1/clips/{id}/stream``'s bytes), or one fetched from a server for a
clip it holds. Each stream is decoded whole ``--repeats`` times and the fastest run is reported
per set: the fastest, because on a shared machine the others measure the neighbours. The
machine, Python and NumPy come first, since the numbers mean nothing without them.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path
from typing import List, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "src"))

import numpy as np  # noqa: E402

import c4g_client as c4g  # noqa: E402


def machine() -> str:
    """The CPU's model name and core count."""
    name = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                name = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{name}, {os.cpu_count()} cores"


def fetch(server: str, clip_id: str, step: float) -> bytes:
    import httpx

    response = httpx.post(f"{server}/v1/clips/{clip_id}/stream", json={"step": step}, timeout=600)
    response.raise_for_status()
    return response.content


def fastest_per_set(data: bytes, repeats: int) -> Tuple[float, int, int]:
    """Seconds per set of the fastest whole decode, sets, Gaussians a set."""
    sets = c4g.decode_c4gv(data)
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        c4g.decode_c4gv(data)
        best = min(best, time.perf_counter() - start)
    return best / max(len(sets), 1), len(sets), len(sets[0]) if sets else 0


def main(argv: List[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("streams", nargs="*", type=Path)
    parser.add_argument("--server")
    parser.add_argument("--clip")
    parser.add_argument("--step", type=float, default=0.01)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args(argv)
    inputs = [(str(path), path.read_bytes()) for path in args.streams]
    if args.server:
        if not args.clip:
            parser.error("--server needs --clip")
        inputs.append((f"{args.clip} at step {args.step}", fetch(args.server, args.clip, args.step)))
    if not inputs:
        parser.error("give stream files, or --server and --clip")
    print(f"machine: {machine()}; Python {platform.python_version()}, NumPy {np.__version__}")
    for name, data in inputs:
        seconds, sets, gaussians = fastest_per_set(data, args.repeats)
        print(
            f"{name}: {sets} sets of {gaussians} Gaussians, {len(data) / max(sets, 1) / 1024:.1f} KiB a set: "
            f"{seconds * 1e3:.3f} ms a set (fastest of {args.repeats})"
        )


if __name__ == "__main__":
    main(sys.argv[1:])
