"""A decoded set written as ``.ply`` and ``.splat`` by the client: read back by readers written
here from the formats' specifications (``formats/src/ply.rs``, ``formats/src/splat.rs``) and by
``plyfile``, and byte for byte the server's own ``ply`` and ``splat`` answers for the same set."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import Client

SH_C0 = 0.28209479177387814
PLY_PROPERTIES = [
    "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
    "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3",
]  # fmt: skip


def a_set(features: bool = False) -> c4g.GaussianSet:
    """Four Gaussians with the extremes a real set has: zero scales (flat Gaussians), opacities
    at 0 and 1, a colour past 1, a rotation that is not quite unit."""
    return c4g.GaussianSet(
        0.25,
        np.float32([[1.0, 2.0, 3.0], [-1.0, 0.5, 2.0], [0.0, 0.0, 1.0], [0.25, -0.125, 4.0]]),
        np.float32([[1.0, 0.0, 0.0, 0.0], [0.5, 0.5, -0.5, 0.5], [0.0, 0.6, 0.0, 0.8], [0.9, 0.1, 0.0, 0.0]]),
        np.float32([[0.1, 0.1, 0.1], [1.0, 2.0, 0.5], [0.0, 0.02, 0.0], [0.0, 0.0, 0.0]]),
        np.float32([0.9, 0.5, 1.0, 0.0]),
        np.float32([[1.0, 0.0, 0.5], [0.2, 0.4, 0.6], [2.0, 0.0, 0.0], [0.3, 0.3, 0.3]]),
        np.arange(8, dtype=np.float32).reshape(4, 2) if features else None,
    )


def read_ply(data: bytes):
    """The header's property names and the rows of a binary little-endian ``.ply`` of float
    properties, one ``vertex`` element."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    lines = data[:end].decode("ascii").splitlines()
    assert lines[:2] == ["ply", "format binary_little_endian 1.0"]
    (count,) = [int(line.split()[2]) for line in lines if line.startswith("element vertex")]
    names = [line.split()[2] for line in lines if line.startswith("property")]
    assert all(line.startswith("property float ") for line in lines if line.startswith("property"))
    return names, np.frombuffer(data[end:], dtype="<f4").reshape(count, len(names))


def expected_ply_rows(s: c4g.GaussianSet) -> np.ndarray:
    """The rows formats/src/ply.rs writes, value by value: float64, the C library's log,
    then float32."""
    rows = []
    for i in range(len(s)):
        o = min(max(float(s.opacities[i]), 1e-7), 1 - 1e-7)
        row = [*s.means[i], 0.0, 0.0, 0.0]
        row += [(float(c) - 0.5) / SH_C0 for c in s.colors[i]]
        row += [math.log(o / (1 - o))]
        row += [math.log(max(float(v), 1e-30)) for v in s.scales[i]]
        row += [*s.quats[i]]
        row += [] if s.features is None else [*s.features[i]]
        rows.append(row)
    return np.float32(rows)


def test_a_ply_holds_the_3dgs_properties_before_activation():
    s = a_set()
    names, rows = read_ply(s.to_ply())
    assert names == PLY_PROPERTIES
    assert rows.tobytes() == expected_ply_rows(s).tobytes()
    # Zero scales are floored at SCALE_FLOOR before their log: finite, the same floor as the
    # set's own log_scales().
    assert c4g.SCALE_FLOOR == 1e-30
    assert np.isfinite(rows).all()
    assert rows[3, 10] == np.float32(math.log(1e-30)) == s.log_scales()[3, 0]
    np.testing.assert_array_equal(rows[:, 10:13], s.log_scales())
    # Opacities 1 and 0 are clamped to 1 ∓ 1e-7: a finite logit either way.
    assert rows[2, 9] == np.float32(math.log((1 - 1e-7) / 1e-7)) == -rows[3, 9]


def test_a_ply_reads_back_to_the_set_as_plyfile_sees_it():
    plyfile = pytest.importorskip("plyfile")
    import io

    s = a_set(features=True)
    vertex = plyfile.PlyData.read(io.BytesIO(s.to_ply()))["vertex"]
    assert [p.name for p in vertex.properties] == PLY_PROPERTIES + ["feat_0", "feat_1"]
    column = lambda *names: np.stack([vertex[n] for n in names], axis=1)  # noqa: E731
    np.testing.assert_array_equal(column("x", "y", "z"), s.means)
    np.testing.assert_array_equal(column("rot_0", "rot_1", "rot_2", "rot_3"), s.quats)
    np.testing.assert_array_equal(column("feat_0", "feat_1"), s.features)
    # Activated again as a 3DGS reader does: exp, sigmoid, SH DC; zero scales come back as
    # 1e-30, opacities within the clamp.
    scales = np.exp(column("scale_0", "scale_1", "scale_2").astype(np.float64))
    np.testing.assert_allclose(scales, np.maximum(s.scales, 1e-30), rtol=2e-6)
    opacities = 1 / (1 + np.exp(-vertex["opacity"].astype(np.float64)))
    np.testing.assert_allclose(opacities, s.opacities, atol=1e-6)
    colors = column("f_dc_0", "f_dc_1", "f_dc_2").astype(np.float64) * SH_C0 + 0.5
    np.testing.assert_allclose(colors, s.colors, atol=1e-6)


SPLAT = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rotation", "u1", 4)])


def test_a_splat_is_32_byte_records_largest_first_without_unwritable_gaussians():
    s = a_set()
    broken = c4g.GaussianSet(
        0.0,
        np.vstack([s.means, [[np.nan, 0, 0], [0, 0, 0]]]).astype(np.float32),
        np.vstack([s.quats, [[1, 0, 0, 0], [0, 0, 0, 0]]]).astype(np.float32),
        np.vstack([s.scales, [[1, 1, 1], [1, 1, 1]]]).astype(np.float32),
        np.concatenate([s.opacities, [1, 1]]).astype(np.float32),
        np.vstack([s.colors, [[0, 0, 0], [0, 0, 0]]]).astype(np.float32),
    )
    data = broken.to_splat()
    assert len(data) == 4 * 32  # a NaN position and a zero rotation are left out
    records = np.frombuffer(data, dtype=SPLAT)
    # scale_x · scale_y · scale_z · opacity: 0.5, 0.0009, 0 and 0; the tie keeps the set's order.
    np.testing.assert_array_equal(records["position"], s.means[[1, 0, 2, 3]])
    np.testing.assert_array_equal(records["scale"], s.scales[[1, 0, 2, 3]])
    # The bytes formats/src/splat.rs's own test expects of the same Gaussians: round(255 v),
    # colours clamped to [0, 1]; round(128 q + 128) of the normalised rotation.
    assert records["rgba"].tolist()[0] == [51, 102, 153, 128]
    assert records["rotation"].tolist()[0] == [192, 192, 64, 192]
    assert records["rgba"].tolist()[2] == [255, 0, 0, 255]
    assert records["rotation"].tolist()[1] == [255, 128, 128, 128]
    # Rust rounds half away from zero, NumPy half to even: 0.5 · 255 = 127.5 is 128.
    assert records["rgba"][0, 3] == 128


def test_a_splat_reads_back_within_its_quantisation():
    s = a_set()
    records = np.frombuffer(s.to_splat(), dtype=SPLAT)
    order = [1, 0, 2, 3]
    np.testing.assert_allclose(records["rgba"][:, 3] / 255, s.opacities[order], atol=1 / 510 + 1e-6)
    np.testing.assert_allclose(
        records["rgba"][:, :3] / 255, np.clip(s.colors[order], 0, 1), atol=1 / 510 + 1e-6
    )
    q = (records["rotation"].astype(np.float64) - 128) / 128
    unit = s.quats[order] / np.linalg.norm(s.quats[order], axis=1, keepdims=True)
    np.testing.assert_allclose(q, unit, atol=1 / 128)


def test_a_set_is_saved_by_its_paths_extension(tmp_path: Path):
    s = a_set()
    s.save(tmp_path / "scene.ply")
    s.save(tmp_path / "scene.SPLAT")
    assert (tmp_path / "scene.ply").read_bytes() == s.to_ply()
    assert (tmp_path / "scene.SPLAT").read_bytes() == s.to_splat()
    with pytest.raises(ValueError, match=r"\.ply or \.splat"):
        s.save(tmp_path / "scene.spz")


def test_an_empty_set_writes_empty_files():
    s = a_set().take(slice(0, 0))
    names, rows = read_ply(s.to_ply())
    assert names == PLY_PROPERTIES and rows.shape == (0, 17)
    assert s.to_splat() == b""


# -- against the server ------------------------------------------------------------------------


def servers_ply(data: bytes) -> bytes:
    """The server's ``.ply`` as the client writes it: the header's comment names the writer."""
    server, client = b"comment written by c4g-renderer\n", b"comment written by c4g-client\n"
    assert data.count(server) == 1
    return data.replace(server, client)


@pytest.mark.parametrize("quality", [None, "fast"])
def test_a_decoded_set_writes_the_servers_own_ply_and_splat(client: Client, clip: c4g.Clip, quality):
    s = client.decode(clip.id, 0.3, quality=quality)
    assert (s.scales == 0).any()  # flat Gaussians, floored in the .ply
    assert s.to_ply() == servers_ply(client.export(clip.id, "ply", t=0.3, quality=quality).data)
    assert s.to_splat() == client.export(clip.id, "splat", t=0.3, quality=quality).data


def test_a_set_with_features_writes_the_servers_ply_with_features(client: Client, clip: c4g.Clip):
    s = client.decode(clip.id, 0.3, features=True)
    served = client.gaussians_raw(clip.id, 0.3, format="ply", features=True)
    assert s.to_ply() == servers_ply(served)
