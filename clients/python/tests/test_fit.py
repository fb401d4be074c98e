"""Fit jobs end to end: submitted through the client, run by a ``c4g-fitter`` worker, followed
as server-sent events with the fit's numbers; the clip then lists its fitted scene, and every
request that takes sets serves it by default, or the feed-forward scene when ``scene=`` asks.

The fits run on clips of their own (the test clip's frames at other rates), so the session's
``clip`` fixture keeps serving its feed-forward scene to the other modules."""

from __future__ import annotations

import asyncio
import math
from typing import List, Tuple

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import AsyncClient, Client

FIELDS = ("means", "quats", "scales", "opacities", "colors")

#: A fit small enough for a test: 40 steps at 32 px on the clip's 7 frames, every 4th held out.
TINY = dict(preset="fast", steps=40, resolution=32, max_frames=8, holdout_every=4, seed=1)


def same_sets(a: List[c4g.GaussianSet], b: List[c4g.GaussianSet]) -> bool:
    return len(a) == len(b) and all(
        getattr(x, name).tobytes() == getattr(y, name).tobytes() for x, y in zip(a, b) for name in FIELDS
    )


@pytest.fixture(scope="module")
def fitted(client: Client, frames, fitter) -> Tuple[c4g.Clip, c4g.Job, List[c4g.Job]]:
    """A clip fitted once for the module: the clip as described after the fit, the fit's last
    record and every record its events showed."""
    clip = client.upload(frames, fps=20)
    assert client.clip(clip.id).fitted is None
    job = client.fit(clip.id, **TINY)
    assert job.kind == "fit" and job.clip_id == clip.id and not job.is_terminal
    seen: List[c4g.Job] = []
    done = client.wait(job.id, progress=seen.append)
    assert done.state == "done", (done.error, fitter.tail())
    return client.clip(clip.id), done, seen


def test_a_fit_reports_its_numbers_as_it_goes(fitted):
    _, done, seen = fitted
    assert done.kind == "fit" and seen[-1] == done
    fitting = [j.progress for j in seen if j.progress is not None and j.progress.stage == "fitting"]
    assert fitting, [j.progress for j in seen]
    last = fitting[-1]
    assert last.steps == TINY["steps"] and 0 < last.step <= last.steps
    assert last.loss is not None and math.isfinite(last.loss)
    assert last.gaussians is not None and last.gaussians > 0
    assert last.elapsed_s is not None and last.elapsed_s > 0
    steps = [p.step for p in fitting]
    assert steps == sorted(steps)


def test_the_clip_lists_its_fitted_scene(fitted):
    clip, done, _ = fitted
    summary = clip.fitted
    assert isinstance(summary, c4g.FittedSummary)
    assert summary.job_id == done.id and summary.preset == "fast" and summary.steps == TINY["steps"]
    # 7 frames, every 4th held out: the one at index 3, never trained on, scored before and after.
    assert summary.frames == 7 and summary.holdout_frames == (3,)
    assert summary.holdout_times == pytest.approx((0.15,))
    assert summary.holdout_psnr is not None and math.isfinite(summary.holdout_psnr)
    assert summary.holdout_gain == pytest.approx(summary.holdout_psnr - summary.holdout_psnr_feed_forward)
    assert 0 < summary.gaussians <= 1_000_000 and 0 <= summary.static_gaussians <= summary.gaussians
    assert max(summary.resolution) <= TINY["resolution"] and summary.keyframes
    assert summary.raw == clip.raw["fitted"]
    assert summary.notes == tuple(clip.raw["fitted"]["notes"])


def test_requests_serve_the_fitted_scene_by_default_and_the_model_s_on_request(client: Client, fitted):
    clip, _, _ = fitted
    times = [0.05, 0.15]
    auto = client.decode(clip.id, times)
    fitted_sets = client.decode(clip.id, times, scene="fitted")
    feed_forward = client.decode(clip.id, times, scene="feed-forward")
    assert same_sets(auto, fitted_sets)
    assert not same_sets(fitted_sets, feed_forward)
    assert len(fitted_sets[0]) == clip.fitted.gaussians

    assert client.render(clip.id, 0.1, width=32, height=32).scene == "fitted"
    view = client.render(clip.id, 0.1, width=32, height=32, scene="feed-forward")
    assert view.scene == "feed-forward" and "feed-forward" in repr(view)
    assert client.render(clip.id, 0.1, width=32, height=32, format="depth").scene == "fitted"
    assert client.export(clip.id, "ply", t=0.1).scene == "fitted"
    export = client.export(clip.id, "ply_zip", step=0.1, scene="feed-forward")
    assert export.scene == "feed-forward" and export.sets == 4
    with client.stream(clip.id, step=0.1) as stream:
        assert stream.scene == "fitted" and len(list(stream)) == 4
    # The fitted scene is served as it was fitted: an approximation of it is refused.
    with pytest.raises(c4g.InvalidInput):
        client.decode(clip.id, 0.1, scene="fitted", quality="fast")


def test_grpc_serves_the_same_fitted_sets(client: Client, fitted):
    pytest.importorskip("grpc")
    clip, _, _ = fitted
    times = [0.0, 0.15, 0.3]
    for scene in ("fitted", "feed-forward"):
        rest = client.decode(clip.id, times, scene=scene)
        assert same_sets(client.grpc_decode(clip.id, times, scene=scene), rest), scene
    assert same_sets(client.grpc_decode(clip.id, times), client.decode(clip.id, times, scene="fitted"))
    with client.grpc_stream(clip.id, start=0.0, end=0.3, step=0.15) as stream:
        sets = list(stream)
        assert stream.scene == "fitted"
    assert same_sets(sets, client.decode(clip.id, times, scene="fitted"))
    with client.grpc_stream(clip.id, step=0.15, scene="feed-forward") as stream:
        assert stream.scene == "feed-forward"


def test_a_clip_without_a_fitted_scene_serves_the_feed_forward_one(client: Client, clip: c4g.Clip):
    assert client.clip(clip.id).fitted is None
    assert client.render(clip.id, 0.3, width=16, height=16).scene == "feed-forward"
    with pytest.raises(c4g.NotFound):
        client.decode(clip.id, 0.3, scene="fitted")


def test_fit_requests_the_server_refuses(client: Client, clip: c4g.Clip):
    with pytest.raises(c4g.InvalidInput):
        client.fit(clip.id, preset="quick")
    with pytest.raises(c4g.InvalidInput):
        client.fit(clip.id, holdout_every=1)
    with pytest.raises(c4g.NotFound):
        client.fit("0" * 24)
    # Refused before a job was made: nothing queued for the clip.
    assert not [j for j in client.jobs() if j.kind == "fit" and j.clip_id == clip.id]


def test_the_async_client_fits_and_a_fit_of_0_steps_serves_the_feed_forward_keyframes(
    server: str, client: Client, frames, fitter
):
    clip = client.upload(frames, fps=25)

    async def body() -> Tuple[c4g.Job, c4g.Clip]:
        async with AsyncClient(server) as c:
            job = await c.fit(clip.id, preset="fast", steps=0, resolution=32, max_frames=8)
            assert job.kind == "fit"
            return await c.wait(job.id), await c.clip(clip.id)

    done, described = asyncio.run(body())
    assert done.state == "done", (done.error, fitter.tail())
    summary = described.fitted
    assert summary is not None and summary.steps == 0 and summary.job_id == done.id
    keyframes = list(summary.keyframes)
    served = client.decode(clip.id, keyframes)
    model = client.decode(clip.id, keyframes, scene="feed-forward")
    for a, b in zip(served, model):
        for name in FIELDS:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
