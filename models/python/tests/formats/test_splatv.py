"""The `.splatv` reader against a file built here byte by byte with `struct` (not with the reader)."""

import json
import math
import struct
import subprocess
import sys

import numpy as np
import pytest

from c4g.formats import splatv

from tests.common import PYTHON_ROOT

N = 1025  # the last Gaussian opens the texture's second row


def half(v: float) -> int:
    return struct.unpack("<H", struct.pack("<e", v))[0]


def h2(a: float, b: float) -> int:
    return half(a) | (half(b) << 16)


def record(i: int) -> list[int]:
    """Gaussian i: simple exactly representable values that tell Gaussians apart."""
    p = [float(i), -1.0, 2.5]
    return [
        *(struct.unpack("<I", struct.pack("<f", v))[0] for v in p),
        h2(1.0, 0.0), h2(0.0, 0.0),  # q = (1, 0, 0, 0)
        h2(0.5, 0.25), h2(0.125, 0.0),  # scales
        10 | (20 << 8) | (30 << 16) | (255 << 24),  # r g b a
        h2(1.0, 2.0), h2(3.0, 0.5), h2(0.0, 0.0), h2(0.0, -1.0), h2(0.0, 0.0),  # v1 v2 v3
        h2(0.0, 1.0), h2(0.0, 0.0),  # omega: about x
        h2(0.25, 0.5),  # trbf centre, scale
    ]


def build(n=N, start=10.0, end=12.0, camera=True) -> bytes:
    rows = -(-n // 1024)
    words = []
    for i in range(rows * 1024):
        words += record(i) if i < n else [0] * 16
    data = struct.pack(f"<{len(words)}I", *words)
    cams = [{"id": 0, "img_name": "a", "width": 224, "height": 224, "position": [0, 0, 0],
             "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "fx": 196.4, "fy": 196.4}]
    chunk = {"type": "splat", "size": len(data), "texwidth": 4096, "texheight": rows,
             "cameras": cams if camera else [], "c4g": {"count": n, "start": start, "end": end}}
    header = json.dumps([{"type": "extra", "size": 3}, chunk]).encode()
    return struct.pack("<II", 0x674B, len(header)) + header + b"xyz" + data


def test_at_matches_hand_computed_values(tmp_path):
    path = tmp_path / "a.splatv"
    path.write_bytes(build())
    model = splatv.read(path)
    assert len(model) == N and model.cameras[0]["fx"] == 196.4
    t = 11.5  # tau = 0.75, dt = 0.5
    got = model.at(t)
    dt = 0.5
    for i in (0, 1023, 1024):
        want = [i + 1.0 * dt + 0.5 * dt**2, -1.0 + 2.0 * dt - 1.0 * dt**3, 2.5 + 3.0 * dt]
        np.testing.assert_allclose(got["positions"][i], want, rtol=1e-6)
    norm = math.hypot(1.0, dt)
    np.testing.assert_allclose(got["rotations"][1024], [1 / norm, dt / norm, 0, 0], rtol=1e-6)
    np.testing.assert_allclose(got["scales"][1024], [0.5, 0.25, 0.125])
    np.testing.assert_allclose(got["colors"][1024], [10 / 255, 20 / 255, 30 / 255], rtol=1e-6)
    np.testing.assert_allclose(got["opacities"][1024], math.exp(-1.0), rtol=1e-6)
    assert model.tau(10.0) == 0.0 and model.tau(12.0) == 1.0


def test_single_set_clip_is_tau_zero_and_no_c4g_is_tau_t(tmp_path):
    model = splatv.parse(build(start=3.0, end=3.0))
    assert model.tau(100.0) == 0.0
    plain = build()
    model = splatv.parse(plain)
    del model.chunk["c4g"]
    assert model.tau(0.25) == 0.25
    np.testing.assert_allclose(model.at(0.25)["opacities"][0], 1.0)


def test_bad_files_raise_clear_errors():
    data = build()
    for cut, words in [(4, "too short"), (20, "truncated"), (len(data) - 1, "truncated")]:
        with pytest.raises(splatv.SplatvError, match=words):
            splatv.parse(data[:cut])
    with pytest.raises(splatv.SplatvError, match="magic"):
        splatv.parse(b"\0" * 16)
    with pytest.raises(splatv.SplatvError, match="cameras"):
        splatv.parse(build(camera=False))


def test_cli_prints_cameras_and_frames(tmp_path):
    path = tmp_path / "a.splatv"
    path.write_bytes(build(n=3))
    out = subprocess.run(
        [sys.executable, "-m", "c4g.formats.splatv", str(path), "--times", "10,11.5"],
        cwd=PYTHON_ROOT, capture_output=True, text=True, check=True,
    ).stdout
    doc = json.loads(out)
    assert doc["cameras"][0]["width"] == 224
    assert [f["time"] for f in doc["frames"]] == [10.0, 11.5]
    assert doc["frames"][1]["positions"][2] == pytest.approx([2.625, -0.125, 4.0])
    assert len(doc["frames"][0]["opacities"]) == 3
