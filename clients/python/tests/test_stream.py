"""The compact 4D stream (C4GV): the client's decoder against the exact sets within the
stream's stated bounds, and against the other decoders bit for bit: the Rust client's (through
``c4g stream --compact``'s PLY files; and, opt-in, the renderer's decoder itself) and the
browser viewer's (``server/viewer/c4gv.js`` under Node)."""

from __future__ import annotations

import math
import os
import shutil
import subprocess
from pathlib import Path
from typing import List

import httpx
import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import Client
from conftest import HERE, REPO, binary

FIELDS = ("means", "quats", "scales", "opacities", "colors")
#: docs/api.md and c4gv.rs: scales (relative), rotations (rad), opacity and colour bounds.
SCALE_ERROR = ROTATION_ERROR = OPACITY_ERROR = COLOR_ERROR = 4.9e-4
SCALE_FLOOR = 2.0**-64


def assert_within_bounds(got: c4g.GaussianSet, exact: c4g.GaussianSet, position_error: float) -> None:
    """Every value of a streamed set against the exact one, in float64, as c4gv.rs states."""
    assert len(got) == len(exact)
    dp = np.abs(got.means.astype(np.float64) - exact.means)
    assert dp.max() <= position_error, dp.max()
    original, decoded = exact.scales.astype(np.float64), got.scales.astype(np.float64)
    relative = np.where(
        original < SCALE_FLOOR,
        np.abs(original - decoded),
        np.abs(decoded / np.where(original < SCALE_FLOOR, 1, original) - 1),
    )
    assert relative.max() <= SCALE_ERROR, relative.max()
    a, b = got.quats.astype(np.float64), exact.quats.astype(np.float64)
    dot = np.abs((a * b).sum(axis=1)) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    angle = 2 * np.arccos(np.minimum(dot, 1.0))
    assert angle.max() <= ROTATION_ERROR, angle.max()
    assert np.abs(got.opacities.astype(np.float64) - exact.opacities).max() <= OPACITY_ERROR
    assert np.abs(got.colors.astype(np.float64) - exact.colors).max() <= COLOR_ERROR


def assert_identical(a: List[c4g.GaussianSet], b: List[c4g.GaussianSet]) -> None:
    assert [s.time for s in a] == [s.time for s in b]
    for x, y in zip(a, b):
        for name in FIELDS:
            assert getattr(x, name).tobytes() == getattr(y, name).tobytes(), (x.time, name)


def raw_stream(server: str, clip_id: str, body: dict) -> bytes:
    response = httpx.post(f"{server}/v1/clips/{clip_id}/stream", json=body, timeout=120)
    assert response.status_code == 200 and response.headers["content-type"] == "application/x-c4g-stream"
    return response.content


def test_streamed_sets_are_the_exact_sets_within_the_streams_bounds(client: Client, clip: c4g.Clip):
    with client.stream(clip.id, step=0.05, keyframe_interval=4) as stream:
        sets = list(stream)
    assert len(sets) == stream.expected == 13
    assert stream.position_error == pytest.approx(1e-3)
    assert [e.keyframe for e in stream.index] == [k % 4 == 0 for k in range(13)]
    exact = client.decode(clip.id, [s.time for s in sets])
    for got, want in zip(sets, exact):
        assert_within_bounds(got, want, 1e-3)


def test_a_finer_bound_is_kept_too(client: Client, clip: c4g.Clip):
    # 1e-4, not the finest 1e-5: that reaches ±10 scene units, and c4g-tiny v2 has a far wall beyond.
    sets = list(client.stream(clip.id, start=0.1, end=0.4, position_error=1e-4))
    exact = client.decode(clip.id, [s.time for s in sets])
    for got, want in zip(sets, exact):
        assert_within_bounds(got, want, 1e-4)


def test_a_fast_stream_keeps_its_bounds_around_the_approximated_sets(client: Client, clip: c4g.Clip):
    with client.stream(clip.id, step=0.05, quality="fast") as stream:
        sets = list(stream)
    assert stream.header is not None and stream.header.gaussians == len(sets[0])
    # The decode endpoint makes the same approximated sets at the same times.
    exact = client.decode(clip.id, [s.time for s in sets], quality="fast")
    for got, want in zip(sets, exact):
        assert_within_bounds(got, want, 1e-3)
        assert len(got) < 512  # fast prunes


def test_the_stream_decodes_the_same_whatever_the_chunks(client: Client, clip: c4g.Clip, server: str):
    data = raw_stream(server, clip.id, {"keyframe_interval": 3})
    whole = c4g.decode_c4gv(data)
    for size in (1, 4096):
        decoder = c4g.C4GVDecoder()
        sets = []
        for at in range(0, len(data), size):
            decoder.feed(data[at : at + size])
            sets.extend(decoder.frames())
        decoder.finish()
        assert_identical(sets, whole)
    assert_identical(list(client.stream(clip.id, keyframe_interval=3)), whole)


def test_a_stream_cut_short_or_corrupt_raises(server: str, clip: c4g.Clip):
    data = raw_stream(server, clip.id, {})
    with pytest.raises(c4g.StreamInterrupted):
        c4g.decode_c4gv(data[: len(data) // 2])
    with pytest.raises(c4g.FormatError):
        c4g.decode_c4gv(data[:-1] + b"X")
    with pytest.raises(c4g.FormatError):
        c4g.decode_c4gv(data + b"\x00")


def test_stream_errors_raise_at_the_call(client: Client, clip: c4g.Clip):
    with pytest.raises(c4g.NotFound):
        client.stream("0" * 24)
    with pytest.raises(c4g.InvalidInput):
        client.stream(clip.id, position_error=2.0)
    with pytest.raises(c4g.InvalidInput):
        client.stream(clip.id, start=0.0, end=9.0)


# -- the other decoders --------------------------------------------------------------------------


SH_C0 = 0.28209479177387814


def ply_rows(s: c4g.GaussianSet) -> np.ndarray:
    """The rows ``c4g-renderer``'s PLY writer makes of a set (formats/src/ply.rs),
    computed the same way: float64, the C library's ``log``, then float32."""
    n = len(s)
    rows = np.zeros((n, 17), dtype=np.float32)
    rows[:, 0:3] = s.means
    rows[:, 6:9] = ((s.colors.astype(np.float64) - 0.5) / SH_C0).astype(np.float32)
    o = np.clip(s.opacities.astype(np.float64), 1e-7, 1 - 1e-7)
    rows[:, 9] = np.array([math.log(v) for v in (o / (1.0 - o)).tolist()], dtype=np.float32)
    scales = np.maximum(s.scales.astype(np.float64), 1e-30)
    rows[:, 10:13] = (
        np.array([math.log(v) for v in scales.reshape(-1).tolist()]).reshape(n, 3).astype(np.float32)
    )
    rows[:, 13:17] = s.quats
    return rows


def read_ply(path: Path) -> np.ndarray:
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode()
    assert "format binary_little_endian" in header and header.count("property float") == 17
    return np.frombuffer(data[end:], dtype="<f4").reshape(-1, 17)


def test_the_decoder_matches_the_rust_client_through_its_ply_files(
    client: Client, clip: c4g.Clip, server: str, tmp_path: Path
):
    """``c4g stream --compact`` decodes the gRPC compact stream with the Rust decoder and writes
    each set as a PLY: positions and rotations raw, colours, opacities and scales through the
    writer's transforms. The same sets decoded here, put through the same transforms, give the
    same float32 bits."""
    out = tmp_path / "cli"
    subprocess.run(
        [
            str(binary("c4g")),
            "--server",
            server,
            "stream",
            clip.id,
            "--compact",
            "1e-3",
            "--step",
            "0.05",
            "-o",
            str(out),
        ],
        check=True,
        capture_output=True,
        timeout=120,
    )
    files = sorted(out.glob("frame-*.ply"))
    with client.grpc_stream(clip.id, step=0.05, compact=1e-3) as stream:
        sets = list(stream)
    assert len(files) == len(sets) == 13
    for path, s in zip(files, sets):
        assert read_ply(path).tobytes() == ply_rows(s).tobytes(), path.name


def test_the_decoder_matches_the_viewers_javascript_reader_bit_for_bit(
    server: str, clip: c4g.Clip, tmp_path: Path
):
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed: the viewer's reader cannot run")
    for body in ({"step": 0.05, "keyframe_interval": 4}, {"quality": "fast", "position_error": 1e-4}):
        data = raw_stream(server, clip.id, body)
        (tmp_path / "s.c4gv").write_bytes(data)
        subprocess.run(
            [
                node,
                str(HERE / "c4gv_node.mjs"),
                str(REPO / "server" / "viewer" / "c4gv.js"),
                str(tmp_path / "s.c4gv"),
                str(tmp_path / "js.c4gs"),
            ],
            check=True,
            capture_output=True,
            timeout=120,
        )
        assert_identical(c4g.decode_c4gv(data), c4g.decode_c4gs((tmp_path / "js.c4gs").read_bytes()))


def rust_dump() -> Path:
    """The renderer's own C4GV decoder as a command (tests/rust_c4gv_dump), built on request:
    ``C4G_RUST_CHECK=1`` builds it (a few minutes: the renderer's crates in a target of its
    own), ``C4G_C4GV_DUMP`` names one already built."""
    given = os.environ.get("C4G_C4GV_DUMP")
    if given:
        return Path(given)
    if os.environ.get("C4G_RUST_CHECK") != "1":
        pytest.skip("opt-in (C4G_RUST_CHECK=1): builds the renderer's C4GV decoder as a command")
    target = Path(os.environ.get("CARGO_TARGET_DIR", REPO / "target" / "c4gv-dump"))
    subprocess.run(
        ["cargo", "build", "-q", "--manifest-path", str(HERE / "rust_c4gv_dump" / "Cargo.toml")],
        check=True,
        timeout=1800,
        env={**os.environ, "CARGO_TARGET_DIR": str(target)},
    )
    return target / "debug" / "c4gv-dump"


def test_the_decoder_matches_the_rust_decoder_bit_for_bit(server: str, clip: c4g.Clip, tmp_path: Path):
    dump = rust_dump()
    bodies = [
        {"step": 0.05, "keyframe_interval": 4},
        {"quality": "fast", "step": 0.02},
        {"position_error": 1e-4, "keyframe_interval": 1},
        {"keyframes": {"count": 3}, "position_error": 0.5},
    ]
    for body in bodies:
        data = raw_stream(server, clip.id, body)
        (tmp_path / "s.c4gv").write_bytes(data)
        subprocess.run(
            [str(dump), str(tmp_path / "s.c4gv"), str(tmp_path / "rust.c4gs")], check=True, timeout=120
        )
        assert_identical(c4g.decode_c4gv(data), c4g.decode_c4gs((tmp_path / "rust.c4gs").read_bytes()))
