"""Reads the service's 4D `.ply.zip` exports with tools that are not ours: Python's `zipfile` and
the `plyfile` package (PyPI), so that tests/e2e/exports.rs checks what another program sees.

A frames zip (formats/src/frames_zip.rs) holds one 3DGS `.ply` per time, named
`frame_000000.ply`, ... in time order, and the times as JSON in the archive's comment:
`{"format": "c4g-frames", "version": 1, "times": [...]}`. Each PLY stores the common 3DGS
columns: positions `x y z`, colour as the degree-0 spherical-harmonic coefficients `f_dc_*`,
opacity as a logit, scales as logarithms, rotation `rot_0..3` as `w x y z`. This reader turns
them back into the values a renderer uses: rgb = 0.5 + C0 * f_dc, opacity = sigmoid, scale = exp,
rotation normalised.

    python -m c4g.formats.frames_zip FILE.ply.zip

prints `{"times": [...], "frames": [{"time", "positions", "scales", "rotations", "opacities",
"colors"}]}` as JSON.
"""

from __future__ import annotations

import argparse
import io
import json
import sys
import zipfile
from importlib.metadata import version

import numpy as np
from plyfile import PlyData

# The degree-0 spherical-harmonic basis constant, 1 / (2 sqrt(pi)).
SH_C0 = 0.28209479177387814


def read(path: str) -> dict:
    """The times and per-time columns of a `.ply.zip`, in renderer units."""
    with zipfile.ZipFile(path) as archive:
        index = json.loads(archive.comment.decode("utf-8"))
        if index.get("format") != "c4g-frames" or index.get("version") != 1:
            raise ValueError(f"{path}: the archive comment is not a c4g-frames index: {index}")
        names = archive.namelist()
        times = index["times"]
        if len(names) != len(times):
            raise ValueError(f"{path}: {len(names)} entries for {len(times)} times")
        if names != sorted(names):
            raise ValueError(f"{path}: entries are not in name order: {names}")
        frames = []
        for time, name in zip(times, names):
            ply = PlyData.read(io.BytesIO(archive.read(name)))
            v = ply["vertex"]
            col = lambda *keys: np.stack([np.asarray(v[k], dtype=np.float64) for k in keys], axis=1)
            rotations = col("rot_0", "rot_1", "rot_2", "rot_3")
            rotations /= np.linalg.norm(rotations, axis=1, keepdims=True)
            frames.append(
                {
                    "time": time,
                    "name": name,
                    "positions": col("x", "y", "z"),
                    "scales": np.exp(col("scale_0", "scale_1", "scale_2")),
                    "rotations": rotations,
                    "opacities": 1.0 / (1.0 + np.exp(-np.asarray(v["opacity"], dtype=np.float64))),
                    "colors": 0.5 + SH_C0 * col("f_dc_0", "f_dc_1", "f_dc_2"),
                }
            )
    return {"times": times, "frames": frames}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("file")
    args = parser.parse_args(argv)
    data = read(args.file)
    out = {
        "reader": f"plyfile {version('plyfile')}",
        "times": data["times"],
        "frames": [
            {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in frame.items()}
            for frame in data["frames"]
        ],
    }
    json.dump(out, sys.stdout)
    sys.stdout.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
