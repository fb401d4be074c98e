"""A reader and evaluator of antimatter15's `.splatv` (the splaTV web player of dynamic splats).

Written from the format's specification (the splaTV viewer, hybrid.js), independently of the
service's writer in formats/src/splatv.rs, so that each can check the other.
NumPy only.

The facts of the format it relies on:
- Bytes 0..8: u32 LE magic 0x674b, u32 LE length L; then L bytes of UTF-8 JSON, an array of
  chunk descriptors, each with a "type" and the "size" of its data in bytes; the chunks' data
  follow the JSON in the array's order. The viewer draws the chunk of type "splat", which also
  holds "texwidth", "texheight" and "cameras" (it opens at cameras[0]: OpenCV axes, "rotation"
  camera-to-world as rows, "position", "fx", "fy" in pixels). Other fields are ignored by the
  viewer; the service adds "c4g": {"count", "start", "end", "times", "fit"}.
- The splat data is an RGBA32UI texture, texwidth x texheight texels of 4 u32. Gaussian i is
  the texels x = ((i & 0x3ff) << 2) + k (k = 0..3), y = i >> 10; with texwidth 4096 that is 16
  consecutive u32 a Gaussian. The viewer draws floor(bytes / 64) Gaussians.
- Per Gaussian, u32 j; h2(a, b) two half floats as GLSL unpackHalf2x16 (a in the low 16 bits):
  j0..2 position (f32); j3, j4 h2(q0, q1), h2(q2, q3) rotation, q0 the scalar; j5, j6
  h2(sx, sy), h2(sz, -) linear scales; j7 bytes r, g, b, a (r lowest), /255; j8..12
  h2(m0x, m0y) .. h2(m4x, -) with v1 = (m0x, m0y, m1x), v2 = (m1y, m2x, m2y), v3 = (m3x, m3y,
  m4x); j13, j14 h2(w0, w1), h2(w2, w3) rotation velocity; j15 h2(trbf_center, trbf_scale).
- At the viewer's time tau, dt = tau - trbf_center: position p + v1 dt + v2 dt^2 + v3 dt^3,
  rotation normalize(q + w dt), opacity a/255 * exp(-(dt / trbf_scale)^2) (the viewer also
  skips Gaussians whose factor is below 0.02; this reader does not); scale and colour constant.
- The viewer's time sweeps 0..1, so tau = (t - start) / (end - start) for the service's clip
  range (0 when start == end); without the "c4g" field, tau = t.

CLI: `python -m c4g.formats.splatv FILE --times 0,0.1,...` prints JSON
{"cameras": [...], "frames": [{"time", "positions", "scales", "rotations", "opacities",
"colors"}]}.
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

MAGIC = 0x674B
TEXTURE_WIDTH = 4096
WORDS = 16


class SplatvError(ValueError):
    """A file that does not follow the format; the message says what and where."""


@dataclass
class Splatv:
    """One `.splatv` file: its splat chunk's descriptor, cameras and per-Gaussian parameters."""

    header: list  # the JSON chunk descriptors, as parsed
    chunk: dict  # the splat chunk's descriptor
    cameras: list  # the splat chunk's cameras, as in the JSON
    position: np.ndarray  # [n, 3] float32
    rotation: np.ndarray  # [n, 4] q0 (scalar) .. q3
    scale: np.ndarray  # [n, 3]
    rgba: np.ndarray  # [n, 4] uint8
    v1: np.ndarray  # [n, 3] position polynomial, dt^1
    v2: np.ndarray  # [n, 3] dt^2
    v3: np.ndarray  # [n, 3] dt^3
    omega: np.ndarray  # [n, 4] rotation velocity
    trbf_center: np.ndarray  # [n]
    trbf_scale: np.ndarray  # [n]

    def __len__(self) -> int:
        return len(self.position)

    @property
    def c4g(self) -> dict | None:
        return self.chunk.get("c4g")

    def tau(self, t_seconds: float) -> float:
        """The viewer's time for `t_seconds`, from the service's clip range when the file has one."""
        meta = self.c4g
        if meta is None:
            return float(t_seconds)
        start, end = float(meta["start"]), float(meta["end"])
        return (t_seconds - start) / (end - start) if end > start else 0.0

    def at(self, t_seconds: float) -> dict:
        """The Gaussians at `t_seconds` (float32, as the viewer's shader computes)."""
        f = np.float32
        dt = (f(self.tau(t_seconds)) - self.trbf_center.astype(f))[:, None]
        pos = self.position + self.v1 * dt + self.v2 * (dt * dt) + self.v3 * (dt * dt * dt)
        q = self.rotation + self.omega * dt
        norm = np.sqrt((q * q).sum(axis=1, keepdims=True))
        with np.errstate(invalid="ignore", divide="ignore"):
            q = np.where(norm > 0, q / norm, np.array([1, 0, 0, 0], f))
        with np.errstate(invalid="ignore", divide="ignore"):
            factor = np.exp(-((dt[:, 0] / self.trbf_scale) ** 2))
        return {
            "positions": pos.astype(f),
            "scales": self.scale.astype(f),
            "rotations": q.astype(f),
            "opacities": (self.rgba[:, 3].astype(f) / f(255) * factor).astype(f),
            "colors": self.rgba[:, :3].astype(f) / f(255),
        }


def _halves(words: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The low and high half floats of u32 words, as float32."""
    low = (words & 0xFFFF).astype(np.uint16).view(np.float16).astype(np.float32)
    high = (words >> 16).astype(np.uint16).view(np.float16).astype(np.float32)
    return low, high


def parse(data: bytes) -> Splatv:
    """Parses `.splatv` bytes."""
    if len(data) < 8:
        raise SplatvError(f"{len(data)} bytes: too short for the 8-byte preamble")
    magic, json_len = struct.unpack_from("<II", data, 0)
    if magic != MAGIC:
        raise SplatvError(f"magic {magic:#x} at byte 0, expected {MAGIC:#x}")
    if 8 + json_len > len(data):
        raise SplatvError(
            f"truncated: the JSON header is {json_len} bytes at byte 8, the file has {len(data) - 8}"
        )
    try:
        header = json.loads(data[8 : 8 + json_len].decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise SplatvError(f"JSON header (bytes 8..{8 + json_len}): {e}") from None
    if not isinstance(header, list):
        raise SplatvError("the JSON header is not an array of chunks")

    offset, found = 8 + json_len, None
    for c, chunk in enumerate(header):
        size = chunk.get("size") if isinstance(chunk, dict) else None
        if not isinstance(size, int) or size < 0:
            raise SplatvError(f"chunk {c} has no byte size")
        if offset + size > len(data):
            raise SplatvError(
                f"truncated: chunk {c} ({chunk.get('type')}) needs bytes {offset}..{offset + size},"
                f" the file has {len(data)}"
            )
        if chunk.get("type") == "splat" and found is None:
            found = (chunk, offset, size)
        offset += size
    if found is None:
        raise SplatvError('no chunk of type "splat"')
    chunk, start, size = found

    width, height = chunk.get("texwidth"), chunk.get("texheight")
    if width != TEXTURE_WIDTH or not isinstance(height, int) or height < 0:
        raise SplatvError(f"texture {width}x{height}: the viewer's layout needs texwidth 4096")
    if size != width * height * 16:
        raise SplatvError(f"splat chunk of {size} bytes for a {width}x{height} RGBA32UI texture")
    cameras = chunk.get("cameras") or []
    if not cameras:
        raise SplatvError("no cameras (the viewer opens at cameras[0])")

    n = size // 64
    meta = chunk.get("c4g")
    if meta is not None:
        count, start_s, end_s = (meta.get(k) if isinstance(meta, dict) else None
                                 for k in ("count", "start", "end"))
        if not isinstance(count, int) or not 0 <= count <= size // 64:
            raise SplatvError(f"c4g.count {count!r} is not a count within the texture's {size // 64}")
        if not all(isinstance(v, (int, float)) and math.isfinite(v) for v in (start_s, end_s)):
            raise SplatvError(f"c4g time range {start_s!r}..{end_s!r} is not two finite numbers")
        n = count

    # Gaussian i at texel (4 * (i & 1023) + k, i >> 10); row-major texels of 4 u32.
    texels = np.frombuffer(data, dtype="<u4", count=size // 4, offset=start).reshape(-1, 4)
    i = np.arange(n)
    first_texel = (i >> 10) * width + ((i & 0x3FF) << 2)
    words = np.concatenate([texels[first_texel + k] for k in range(4)], axis=1)  # [n, 16]

    lo, hi = _halves(words)
    rgba = words[:, 7].astype("<u4").view(np.uint8).reshape(n, 4)  # r lowest byte
    return Splatv(
        header=header,
        chunk=chunk,
        cameras=cameras,
        position=words[:, 0:3].copy().view("<f4").astype(np.float32),
        rotation=np.stack([lo[:, 3], hi[:, 3], lo[:, 4], hi[:, 4]], axis=1),
        scale=np.stack([lo[:, 5], hi[:, 5], lo[:, 6]], axis=1),
        rgba=rgba,
        v1=np.stack([lo[:, 8], hi[:, 8], lo[:, 9]], axis=1),
        v2=np.stack([hi[:, 9], lo[:, 10], hi[:, 10]], axis=1),
        v3=np.stack([lo[:, 11], hi[:, 11], lo[:, 12]], axis=1),
        omega=np.stack([lo[:, 13], hi[:, 13], lo[:, 14], hi[:, 14]], axis=1),
        trbf_center=lo[:, 15],
        trbf_scale=hi[:, 15],
    )


def read(path) -> Splatv:
    """Reads a `.splatv` file."""
    return parse(Path(path).read_bytes())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("file")
    parser.add_argument("--times", required=True, help="comma-separated times in seconds")
    args = parser.parse_args(argv)
    try:
        model = read(args.file)
    except (OSError, SplatvError) as e:
        print(f"{args.file}: {e}", file=sys.stderr)
        return 1
    frames = []
    for t in (float(v) for v in args.times.split(",") if v.strip()):
        values = model.at(t)
        frames.append({"time": t, **{k: v.tolist() for k, v in values.items()}})
    json.dump({"cameras": model.cameras, "frames": frames}, sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
