"""Every REST operation of the blocking client against the real server, and the error mapping.

The acceptance checks of the issue are here too: the arrays a decode returns equal the server's
JSON exactly, and a render through the client is byte for byte the render fetched with plain
httpx (and with curl where it is installed).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import zipfile
from io import BytesIO
from pathlib import Path

import httpx
import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import Client

FIELDS = ("means", "quats", "scales", "opacities", "colors")


def assert_sets_equal(a: c4g.GaussianSet, b: c4g.GaussianSet) -> None:
    assert a.time == b.time
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype == np.float32
        np.testing.assert_array_equal(x, y, err_msg=name)


def test_the_service_reports_its_model_and_readiness(client: Client):
    (model,) = client.models()
    assert model.name == "c4g-tiny" and model.gaussians_per_set == 512
    assert model.input_width == model.input_height == 64
    assert model.limits["max_times"] >= 1
    assert client.ready()
    assert not Client("http://127.0.0.1:9").ready()


def test_an_upload_of_frames_is_a_clip_with_its_context_span(clip: c4g.Clip, frames):
    assert clip.state == "ready" and clip.model == "c4g-tiny"
    assert clip.source.kind == "images" and clip.source.frames == len(frames) == 7
    assert clip.span == (0.0, 0.6) and clip.context_times[0] == 0.0
    assert len(clip.id) == 24


def test_uploads_of_a_folder_bytes_and_arrays_with_progress(
    client: Client, clip: c4g.Clip, frames, tmp_path: Path
):
    folder = tmp_path / "frames"
    folder.mkdir()
    for f in frames:
        shutil.copy(f, folder / f.name)
    seen = []
    again = client.upload(folder, fps=10, progress=lambda sent, total: seen.append((sent, total)))
    # The same bytes with the same options are the same clip, not encoded again.
    assert again.id == clip.id and again.created is False
    total = seen[-1][1]
    assert seen[0] == (0, total) and seen[-1] == (total, total)
    assert all(a[0] <= b[0] for a, b in zip(seen, seen[1:]))

    from c4g_client import _png

    arrays = [_png.decode(f.read_bytes())[:, :, :3] for f in frames]
    times = [0.0, 0.1, 0.25, 0.3, 0.4, 0.5, 0.65]
    from_arrays = client.upload(arrays, times=times)
    assert from_arrays.source.frames == 7 and from_arrays.span[1] == pytest.approx(0.65)

    archive = BytesIO()
    with zipfile.ZipFile(archive, "w") as z:
        for f in frames:
            z.write(f, f.name)
    from_bytes = client.upload(archive.getvalue(), content_type="application/zip", max_frames=3)
    assert len(from_bytes.context_times) == 3
    zip_path = tmp_path / "clip.zip"
    zip_path.write_bytes(archive.getvalue())
    from_path = client.upload(zip_path, max_frames=3)
    assert from_path.id == from_bytes.id

    # A video file: the server's own MP4 of an orbit, uploaded back by path.
    video = tmp_path / "orbit.mp4"
    client.render_video(clip.id, c4g.Orbit(2.0, 15), frames=6, fps=12, width=64, height=64, path=video)
    from_video = client.upload(video, end=0.4)
    assert from_video.source.kind == "video" and from_video.source.frames == 6


def test_clips_are_listed_described_and_deleted(client: Client, clip: c4g.Clip, frames):
    extra = client.upload(frames[:4], fps=5)
    described = client.clip(extra.id)
    assert (described.id, described.span, described.context_times) == (
        extra.id,
        extra.span,
        extra.context_times,
    )
    ids = [c.id for c in client.clips()]
    assert clip.id in ids and extra.id in ids
    client.delete_clip(extra.id)
    with pytest.raises(c4g.NotFound) as e:
        client.clip(extra.id)
    assert e.value.status == 404 and e.value.kind == "not_found" and "no clip" in e.value.message


def test_context_frames_are_images(client: Client, clip: c4g.Clip):
    frame = client.context_frame(clip.id, 1)
    assert frame.array.shape == (64, 64, 3) and frame.array.dtype == np.uint8
    with pytest.raises(c4g.NotFound):
        client.context_frame(clip.id, 99)


def test_a_decode_equals_the_servers_json_exactly(client: Client, clip: c4g.Clip):
    times = [0.0, 0.15, 0.3, 0.6]
    sets = client.decode(clip.id, times)
    body = json.loads(client.gaussians_raw(clip.id, times, format="json"))
    assert [s.time for s in sets] == [f["t"] for f in body["frames"]] == times
    for s, frame in zip(sets, body["frames"]):
        assert len(s) == frame["count"] == 512
        np.testing.assert_array_equal(s.means, np.float32(frame["means"]))
        np.testing.assert_array_equal(s.quats, np.float32(frame["rotations"]))
        np.testing.assert_array_equal(s.scales, np.float32(frame["scales"]))
        np.testing.assert_array_equal(s.opacities, np.float32(frame["opacities"]))
        np.testing.assert_array_equal(s.colors, np.float32(frame["colors"]))
    one = client.decode(clip.id, 0.3)
    assert isinstance(one, c4g.GaussianSet)
    assert_sets_equal(one, sets[2])


def test_gsplat_conventions_hold_for_decoded_sets(client: Client, clip: c4g.Clip):
    s = client.decode(clip.id, 0.3)
    assert s.means.shape == (512, 3) and s.quats.shape == (512, 4) and s.scales.shape == (512, 3)
    assert s.opacities.shape == (512,) and s.colors.shape == (512, 3)
    np.testing.assert_allclose(np.linalg.norm(s.quats, axis=1), 1.0, atol=1e-6)
    # Linear scales (the server's exp of the model's log scales), activated opacities.
    assert (s.scales >= 0).all() and s.scales.max() < 10
    assert ((s.opacities >= 0) & (s.opacities <= 1)).all()


def test_f16_decodes_are_the_exact_sets_rounded_to_half(client: Client, clip: c4g.Clip):
    exact = client.decode(clip.id, [0.1, 0.5])
    half = client.decode(clip.id, [0.1, 0.5], precision="f16")
    for e, h in zip(exact, half):
        for name in FIELDS:
            value = getattr(e, name)
            rounded = np.clip(value, -65504, 65504).astype(np.float16).astype(np.float32)
            np.testing.assert_array_equal(getattr(h, name), rounded, err_msg=name)


def test_quality_keyframes_and_prune_pass_through(client: Client, clip: c4g.Clip):
    times = [0.0, 0.1, 0.2, 0.3]
    pruned = client.decode(clip.id, times, prune=c4g.Prune(contribution_px=0.5))
    assert all(len(s) == len(pruned[0]) < 512 for s in pruned)
    keyed = client.decode(clip.id, times, keyframes=c4g.Keyframes.count(2))
    exact = client.decode(clip.id, times)
    assert_sets_equal(keyed[0], exact[0])
    assert not np.array_equal(keyed[1].means, exact[1].means)
    fast = client.decode(clip.id, times, quality="fast", keyframes={"every_s": 0.1})
    assert len(fast) == 4
    with pytest.raises(c4g.InvalidInput, match="keyframes|count"):
        client.decode(clip.id, times, keyframes={"count": 1})


def test_errors_carry_the_servers_kind_status_and_message(client: Client, clip: c4g.Clip, server: str):
    with pytest.raises(c4g.InvalidInput) as e:
        client.decode(clip.id, 5.0)
    assert (e.value.status, e.value.kind) == (400, "invalid_input")
    assert "outside the clip's context span" in e.value.message
    with pytest.raises(c4g.NotFound) as e:
        client.decode("0" * 24, 0.1)
    assert e.value.kind == "not_found"
    with pytest.raises(c4g.UnsupportedMedia):
        client.upload(b"this is not a video", content_type="application/octet-stream")
    with pytest.raises(c4g.InvalidInput):
        client.render(clip.id, 0.1, width=0)
    with pytest.raises(c4g.TransportError):
        Client("http://127.0.0.1:9").models()


def test_a_render_through_the_client_is_the_render_fetched_with_plain_httpx(
    client: Client, clip: c4g.Clip, server: str
):
    body = {"t": 0.3, "width": 80, "height": 48, "background": [0.1, 0.2, 0.3]}
    image = client.render(clip.id, 0.3, width=80, height=48, background=(0.1, 0.2, 0.3))
    plain = httpx.post(f"{server}/v1/clips/{clip.id}/render", json=body, timeout=60)
    assert plain.status_code == 200 and plain.headers["content-type"] == "image/png"
    assert image.png == plain.content
    assert image.time == 0.3 and image.array.shape == (48, 80, 3)
    if shutil.which("curl"):
        curl = subprocess.run(
            [
                "curl",
                "-fsS",
                "-X",
                "POST",
                "-H",
                "Content-Type: application/json",
                "-d",
                json.dumps(body),
                f"{server}/v1/clips/{clip.id}/render",
            ],
            check=True,
            capture_output=True,
            timeout=60,
        ).stdout
        assert image.png == curl


def test_renders_take_cameras_and_give_depth_and_alpha(client: Client, clip: c4g.Clip):
    moved = np.eye(4)
    moved[0, 3] = 0.05
    camera = c4g.Camera(moved, c4g.Intrinsics(fx=0.9, fy=0.9))
    image = client.render(clip.id, 0.2, camera=camera, width=32, height=32)
    default = client.render(clip.id, 0.2, width=32, height=32)
    assert image.png != default.png
    as_dict = client.render(clip.id, 0.2, camera=camera.to_json(), width=32, height=32)
    assert as_dict.png == image.png
    depth = client.render(clip.id, 0.2, width=32, height=24, format="depth")
    alpha = client.render(clip.id, 0.2, width=32, height=24, format="alpha")
    assert depth.array.shape == alpha.array.shape == (24, 32) and depth.array.dtype == np.float32
    assert 0 <= alpha.array.min() and alpha.array.max() <= 1 and depth.array.max() > 0
    pruned = client.render(clip.id, 0.2, width=32, height=32, quality="fast")
    assert pruned.array.shape == (32, 32, 3)


def test_videos_render_along_presets_and_cameras(client: Client, clip: c4g.Clip, tmp_path: Path):
    path = tmp_path / "orbit.mp4"
    video = client.render_video(
        clip.id, c4g.Orbit(depth=2.0, angle_degrees=20), frames=4, width=32, height=32, path=path
    )
    assert video.data[4:8] == b"ftyp" and path.read_bytes() == video.data
    cameras = [c4g.Camera(), c4g.Camera(np.eye(4))]
    assert (
        client.render_video(
            clip.id, cameras=cameras, width=32, height=32, keyframes=c4g.Keyframes.count(2)
        ).data[4:8]
        == b"ftyp"
    )
    with pytest.raises(ValueError):
        client.render_video(clip.id)


@pytest.mark.parametrize("format,magic", [("ply_zip", b"PK"), ("spz_zip", b"PK"), ("splatv", None)])
def test_exports_of_a_time_range(client: Client, clip: c4g.Clip, tmp_path: Path, format, magic):
    path = tmp_path / f"clip.{format}"
    export = client.export(clip.id, format, start=0.0, end=0.3, step=0.1, path=path)
    assert export.sets == 4 and path.read_bytes() == export.data
    assert export.filename and export.filename.startswith(clip.id[:12])
    if magic:
        assert export.data.startswith(magic)
    else:
        assert set(export.fit_error) == {"max", "rms"}


def test_one_time_exports_as_ply_and_splat(client: Client, clip: c4g.Clip):
    ply = client.export(clip.id, "ply", t=0.3)
    assert ply.data.startswith(b"ply\n") and b"element vertex 512" in ply.data
    splat = client.export(clip.id, "splat", t=0.3)
    assert len(splat.data) == 32 * 512
    with pytest.raises(ValueError):
        client.export(clip.id, "ply")
