"""The evaluation protocols: the committed fixtures are what the generator makes, the LK baseline
follows a translating texture, and the runner (against a fake service) scores what it is given."""

from __future__ import annotations

import io
import json
import re
from pathlib import Path

import httpx
import numpy as np
import pytest
from PIL import Image

from c4g.eval import fixtures as eval_fixtures, protocols as eval_protocols, world as eval_world, lk_baseline, tapvid

from tests.common import MODELS

FIXTURES = MODELS / "fixtures" / "eval"


def _image(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path)).astype(int)


def _numbers(value):
    """The numbers of a parsed JSON value, in order, and its shape without them."""
    if isinstance(value, dict):
        return [n for k in sorted(value) for n in _numbers(value[k])]
    if isinstance(value, list):
        return [n for v in value for n in _numbers(v)]
    return [value] if isinstance(value, (int, float)) and not isinstance(value, bool) else []


def _same_clip(made: Path, committed: Path) -> None:
    """Tolerances, for machines whose floating point differs in the last bits (on the machine that
    made the fixtures the bytes are equal): JSON numbers to 1e-9, frames to one 8-bit level, masks
    on all but 0.5% of pixels, tracks to 1e-5 px with at most one occlusion flag changed."""
    files = sorted(p.relative_to(committed) for p in committed.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(made) for p in made.rglob("*") if p.is_file())
    for rel in files:
        a, b = made / rel, committed / rel
        if a.read_bytes() == b.read_bytes():
            continue
        if rel.suffix == ".json":
            ja, jb = json.loads(a.read_text()), json.loads(b.read_text())
            np.testing.assert_allclose(_numbers(ja), _numbers(jb), atol=1e-9, err_msg=str(rel))
        elif rel.parts[0] == "masks":
            assert (_image(a) != _image(b)).mean() <= 0.005, rel
        elif rel.suffix == ".png":
            assert np.abs(_image(a) - _image(b)).max() <= 1, rel
        else:
            (_, fa), = tapvid.load(a).items()
            (_, fb), = tapvid.load(b).items()
            assert np.abs(fa.video.astype(int) - fb.video).max() <= 1
            np.testing.assert_allclose(fa.pixels(), fb.pixels(), atol=1e-5)
            assert (fa.occluded != fb.occluded).sum() <= 1
            np.testing.assert_array_equal(fa.times, fb.times)


@pytest.mark.parametrize("world,seed", [("world1", 2000037), ("eval", 3)])
def test_the_committed_fixtures_are_what_the_generator_makes(tmp_path, world, seed):
    entry = eval_fixtures.write_clip(tmp_path, world, seed, list(eval_fixtures.CONTEXT))
    _same_clip(tmp_path / entry["name"], FIXTURES / entry["name"])
    manifest = json.loads((FIXTURES / "manifest.json").read_text())
    assert entry in manifest["clips"]
    assert manifest["command"] == eval_fixtures.COMMAND


def test_the_committed_fixtures_stay_small_and_well_formed():
    size = sum(p.stat().st_size for p in FIXTURES.rglob("*") if p.is_file())
    assert size < 2_000_000
    for folder in sorted(p for p in FIXTURES.iterdir() if p.is_dir()):
        clip = eval_protocols.load_clip(folder)
        assert clip.context == list(eval_fixtures.CONTEXT) and clip.held_out == [1, 2, 4, 5, 6, 8, 9]
        assert len(clip.cameras) == len(clip.frames_png) == 11
        # Every queried track is visible at its query frame, which is a context frame.
        q = clip.tracks.query_frame
        assert np.isin(q[q >= 0], eval_fixtures.CONTEXT).all()
        assert not clip.tracks.occluded[q >= 0, q[q >= 0]].any()
        # The posed frames' cameras are the upload's, and frames and video agree.
        np.testing.assert_allclose(clip.world_to_camera.reshape(11, 16), [c["world_to_camera"] for c in clip.cameras], atol=1e-9)
        np.testing.assert_array_equal(np.stack([eval_protocols._decode(p) for p in clip.frames_png]), clip.tracks.video)


def test_eval_world_tracks_land_on_the_objects_they_follow():
    scene = eval_world.make_scene(3)
    times = np.array([0.0, 0.5])
    frames, depth, w2c = eval_world.render(scene, times, 64)
    pts, uv, visible = eval_world.tracks(scene, times, 64, depth, w2c)
    assert pts.shape[1] == eval_world.TRACKS_PER_THING * len(scene.things) and visible.any()
    # A visible tracked point is at the rendered surface: its depth is the depth map's there.
    cam = np.einsum("tij,tkj->tki", w2c[:, :3, :3], pts) + w2c[:, None, :3, 3]
    px = uv.astype(int)
    t, k = np.nonzero(visible)
    surface = depth[t, px[t, k, 1], px[t, k, 0]]
    assert np.median(np.abs(cam[t, k, 2] / surface - 1)) < 0.05


def _translating_texture(velocity, frames=11, size=64, seed=0):
    """A smooth, non-repeating texture moving `velocity` px per frame, sampled exactly (a sum of
    random plane waves): frame t shows the texture at x - velocity * t."""
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(40, 2)) * 0.35
    phase = rng.uniform(0, 2 * np.pi, 40)
    y, x = np.mgrid[0:size, 0:size] + 0.5
    out = []
    for t in range(frames):
        u, v = x - velocity[0] * t, y - velocity[1] * t
        g = np.cos(u[..., None] * k[:, 0] + v[..., None] * k[:, 1] + phase).sum(-1)
        g = 128 + 90 * g / np.abs(g).max()
        out.append(np.repeat(np.round(g).astype(np.uint8)[..., None], 3, axis=-1))
    return np.stack(out)


def test_lk_recovers_a_translating_texture_within_a_pixel():
    v = np.array([1.3, -0.7])
    video = _translating_texture(v)
    query_frame = np.array([0, 5, 10, 3])
    query_xy = np.array([[20.5, 36.0], [32.2, 30.7], [45.0, 25.5], [28.0, 33.0]])
    truth = query_xy[:, None, :] + (np.arange(11)[None, :, None] - query_frame[:, None, None]) * v
    points, occluded = lk_baseline.track(video, query_frame, query_xy)
    assert np.linalg.norm(points - truth, axis=-1).max() < 1.0
    assert not occluded.any()
    # Over the context frames alone, linear between them: still exact for a steady motion.
    context = np.array([0, 3, 7, 10])
    points, occluded = lk_baseline.track_context_only(video, context, np.array([0, 3, 10, 3]), truth[[0, 3, 2, 3], [0, 3, 10, 3]])
    truth = truth[[0, 3, 2, 3]]
    assert np.linalg.norm(points - truth, axis=-1).max() < 1.0
    assert not occluded.any()


def test_lk_calls_a_point_lost_when_its_texture_vanishes():
    video = _translating_texture(np.array([1.0, 0.0]))
    video[6:] = 128  # the texture is gone from frame 6 on
    points, occluded = lk_baseline.track(video, np.array([0]), np.array([[30.0, 30.0]]))
    assert not occluded[0, :6].any() and occluded[0, 6:].all()
    np.testing.assert_allclose(points[0, 6:], points[0, 5:6].repeat(5, 0))


class FakeService:
    """A service that answers the protocols' calls perfectly from a fixture's ground truth (its
    renders two 8-bit levels too bright), and records what it was asked."""

    def __init__(self, folder: Path):
        self.clip = eval_protocols.load_clip(folder)
        self.asked: dict[str, object] = {}
        ctx = self.clip.context
        w2c = self.clip.world_to_camera
        # The server's model frame, written here from docs/api.md on its own.
        centres = np.stack([-m[:3, :3].T @ m[:3, 3] for m in w2c[ctx]])
        largest = float(np.linalg.norm(centres - centres[0], axis=1).max())
        self.scale = largest if largest > 1e-9 else 1.0  # a still camera keeps its units
        rel = w2c @ np.linalg.inv(w2c[ctx[0]])
        rel[:, :3, 3] /= self.scale
        self.model_frame = rel

    def __call__(self, request: httpx.Request) -> httpx.Response:
        path, times = request.url.path, self.clip.times
        if path == "/v1/models":
            return httpx.Response(200, json={"name": "fake"})
        if request.method == "POST" and path == "/v1/clips":
            body = request.read()
            self.asked["frames"] = body.count(b'name="frame"')
            self.asked["fields"] = dict(re.findall(rb'name="(start|end|max_frames)"\r\n\r\n([^\r]*)', body))
            ctx = self.clip.context
            return httpx.Response(201, json={
                "id": "fake1", "context_times": times[ctx].tolist(), "span": [times[ctx[0]], times[ctx[-1]]],
                "cameras": {"scale": self.scale, "frames": [{"t": times[i], "world_to_camera": self.model_frame[i].ravel().tolist()} for i in ctx]},
            })  # fmt: skip
        if path.endswith("/tracks"):
            body = json.loads(request.read())
            px = self.clip.tracks.pixels()
            out = []
            for q in body["queries"]:
                f = int(np.argmin(np.abs(times - q["t"])))
                k = int(np.argmin(np.linalg.norm(px[:, f] - [q["x"], q["y"]], axis=1)))
                points = [{"t": t, "x": px[k, int(np.argmin(np.abs(times - t))), 0], "y": px[k, int(np.argmin(np.abs(times - t))), 1],
                           "visible": not bool(self.clip.tracks.occluded[k, int(np.argmin(np.abs(times - t)))])} for t in body["times"]]  # fmt: skip
                out.append({"query": q, "anchored": True, "points": points})
            return httpx.Response(200, json={"width": body["width"], "height": body["height"], "times": body["times"], "tracks": out})
        if path.endswith("/render"):
            body = json.loads(request.read())
            f = int(np.argmin(np.abs(times - body["t"])))
            np.testing.assert_allclose(body["camera"]["world_to_camera"], self.model_frame[f].ravel(), atol=1e-9)
            frame = np.clip(self.clip.tracks.video[f].astype(int) + 2, 0, 255).astype(np.uint8)
            buf = io.BytesIO()
            Image.fromarray(frame).save(buf, format="PNG")
            return httpx.Response(200, content=buf.getvalue(), headers={"content-type": "image/png"})
        if request.method == "DELETE":
            self.asked["deleted"] = path
            return httpx.Response(204)
        return httpx.Response(404, json={"error": f"no {path}", "kind": "not_found"})


def test_the_runner_scores_a_perfect_service_perfectly_and_lk_below_it(tmp_path, capsys):
    folder = FIXTURES / "world1-2000015"
    fake = FakeService(folder)
    out = tmp_path / "report.json"
    assert eval_protocols.main([str(folder), "--server", "http://fake", "--json", str(out)], transport=httpx.MockTransport(fake)) == 0
    assert fake.asked["frames"] == 11
    assert fake.asked["fields"] == {b"start": b"0.0", b"end": b"1.0", b"max_frames": b"4"}
    assert fake.asked["deleted"] == "/v1/clips/fake1"
    report = json.loads(out.read_text())
    (clip,) = report["clips"]
    assert clip["context_frames"] == [0, 3, 7, 10]
    for split in ("context", "interpolated"):
        service = clip["tracking"][eval_protocols.SERVICE][split]
        assert service["delta_avg"] == service["average_jaccard"] == service["occlusion_accuracy"] == 1.0
        for lk in (eval_protocols.LK_ALL, eval_protocols.LK_CONTEXT):
            assert 0 <= clip["tracking"][lk][split]["average_jaccard"] < 1
    views = clip["views"][eval_protocols.SERVICE]
    # Two levels off everywhere (no pixel of these frames is above 253): 20 log10(255 / 2) dB.
    assert views["held_out"]["psnr"] == pytest.approx(20 * np.log10(255 / 2), abs=0.05)
    assert [r["frame"] for r in views["held_out"]["frames"]] == [1, 2, 4, 5, 6, 8, 9]
    assert len(views["context"]["frames"]) == 4
    assert np.isfinite(clip["views"][eval_protocols.CROSSFADE]["held_out"]["psnr"])
    printed = capsys.readouterr().out
    assert "| world1 (1) | c4g (Gaussian trajectories) | interpolated | 1.000 |" in printed


def test_the_runner_refuses_a_server_that_chose_other_context_frames():
    folder = FIXTURES / "world1-2000037"
    fake = FakeService(folder)
    fake.clip.context = [0, 5, 10]  # the fake answers with these; the folder declares 0, 3, 7, 10
    service = eval_protocols.Service("http://fake", transport=httpx.MockTransport(fake))
    with pytest.raises(RuntimeError, match="context times"):
        eval_protocols.evaluate_clip(service, eval_protocols.load_clip(folder))
    assert fake.asked["deleted"] == "/v1/clips/fake1"
