"""Every operation of the asyncio client against the real server: the same answers as the
blocking client's (each test runs its own event loop with ``asyncio.run``)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any, Awaitable, Callable

import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import AsyncClient, Client

FIELDS = ("means", "quats", "scales", "opacities", "colors")


def run(server: str, body: Callable[[AsyncClient], Awaitable[Any]]) -> Any:
    async def main() -> Any:
        async with AsyncClient(server) as client:
            return await body(client)

    return asyncio.run(main())


def same_sets(a, b) -> None:
    assert [s.time for s in a] == [s.time for s in b]
    for x, y in zip(a, b):
        for name in FIELDS:
            assert getattr(x, name).tobytes() == getattr(y, name).tobytes()


def test_async_service_and_clips(server: str, client: Client, clip: c4g.Clip, frames):
    async def body(c: AsyncClient):
        assert await c.ready()
        (model,) = await c.models()
        progress = []
        again = await c.upload(frames, fps=10, progress=lambda sent, total: progress.append(sent))
        other = await c.upload(frames[:3], fps=4)
        listed = [x.id for x in await c.clips()]
        described = await c.clip(other.id)
        frame = await c.context_frame(clip.id, 0)
        await c.delete_clip(other.id)
        with pytest.raises(c4g.NotFound):
            await c.clip(other.id)
        return model, again, progress, listed, described, other, frame

    model, again, progress, listed, described, other, frame = run(server, body)
    assert model.name == "c4g-tiny"
    assert again.id == clip.id and again.created is False and progress[0] == 0
    assert clip.id in listed and other.id in listed and described.id == other.id
    assert frame.png == client.context_frame(clip.id, 0).png


def test_async_decodes_renders_and_exports_equal_the_blocking_clients(
    server: str, client: Client, clip: c4g.Clip, tmp_path: Path
):
    async def body(c: AsyncClient):
        return (
            await c.decode(clip.id, [0.1, 0.4]),
            await c.decode(clip.id, 0.2, precision="f16"),
            await c.gaussians_raw(clip.id, 0.2, format="json"),
            await c.render(clip.id, 0.3, width=40, height=30),
            await c.render(clip.id, 0.3, width=40, height=30, format="alpha"),
            await c.render_video(
                clip.id, c4g.Dolly(distance=0.2), frames=3, width=32, height=32, path=tmp_path / "v.mp4"
            ),
            await c.export(clip.id, "splatv", step=0.2, path=tmp_path / "c.splatv"),
        )

    sets, half, raw, image, alpha, video, export = run(server, body)
    same_sets(sets, client.decode(clip.id, [0.1, 0.4]))
    same_sets([half], [client.decode(clip.id, 0.2, precision="f16")])
    assert raw == client.gaussians_raw(clip.id, 0.2, format="json")
    assert image.png == client.render(clip.id, 0.3, width=40, height=30).png
    np.testing.assert_array_equal(
        alpha.array, client.render(clip.id, 0.3, width=40, height=30, format="alpha").array
    )
    assert video.data[4:8] == b"ftyp" and (tmp_path / "v.mp4").read_bytes() == video.data
    assert export.sets == 4 and (tmp_path / "c.splatv").read_bytes() == export.data


def test_async_streams_equal_the_blocking_clients(server: str, client: Client, clip: c4g.Clip):
    pytest.importorskip("grpc")

    async def body(c: AsyncClient):
        stream = await c.stream(clip.id, step=0.1, keyframe_interval=2)
        compact = [s async for s in stream]
        async with await c.grpc_stream(clip.id, step=0.1) as g:
            packed = [s async for s in g]
        grpc_compact = [
            s async for s in await c.grpc_stream(clip.id, step=0.1, compact=1e-3, keyframe_interval=2)
        ]
        with pytest.raises(c4g.NotFound):
            await c.stream("0" * 24)
        with pytest.raises(c4g.InvalidInput):
            await c.grpc_stream(clip.id, start=0.0, end=9.0)
        return compact, stream.expected, packed, grpc_compact

    compact, expected, packed, grpc_compact = run(server, body)
    assert expected == len(compact) == 7
    same_sets(compact, list(client.stream(clip.id, step=0.1, keyframe_interval=2)))
    same_sets(grpc_compact, compact)
    same_sets(packed, client.decode(clip.id, [s.time for s in packed]))


def test_async_grpc_calls_share_one_channel_that_aclose_closes(server: str, clip: c4g.Clip, monkeypatch):
    grpc = pytest.importorskip("grpc")
    opened = []
    open_channel = grpc.aio.insecure_channel

    def counted(*args, **kwargs):
        opened.append(open_channel(*args, **kwargs))
        return opened[-1]

    monkeypatch.setattr(grpc.aio, "insecure_channel", counted)

    async def body(c: AsyncClient):
        assert opened == []
        streamed = [s async for s in await c.grpc_stream(clip.id, start=0.0, end=0.1, step=0.1)]
        decoded = await c.grpc_decode(clip.id, [0.2, 0.3])
        return len(streamed), len(decoded), len(opened)

    assert run(server, body) == (2, 2, 1)
    assert opened[0].get_state() == grpc.ChannelConnectivity.SHUTDOWN


def test_async_jobs_and_errors(server: str, clip: c4g.Clip):
    async def body(c: AsyncClient):
        job = await c.refine(
            clip.id, steps=2, trajectory={"kind": "orbit", "depth": 2.0, "angle_degrees": 10}
        )
        listed = [j.id for j in await c.jobs()]
        fetched = await c.job(job.id)
        cancelled = await c.cancel(job.id)
        events = [j async for j in await c.follow(job.id)]
        waited = await c.wait(job.id)
        with pytest.raises((c4g.InvalidInput, c4g.NotFound)):
            await c.job_result(job.id)
        with pytest.raises((c4g.InvalidInput, c4g.NotFound)):
            await c.job_frame(job.id, 0)
        with pytest.raises(c4g.InvalidInput) as e:
            await c.decode(clip.id, 7.5)
        return job, listed, fetched, cancelled, events, waited, e.value

    job, listed, fetched, cancelled, events, waited, error = run(server, body)
    assert job.id in listed and fetched.id == job.id
    assert cancelled.state == events[-1].state == waited.state == "cancelled"
    assert (error.status, error.kind) == (400, "invalid_input")


def test_async_refine_end_to_end(server: str, clip: c4g.Clip, refiner):
    async def body(c: AsyncClient):
        job = await c.refine(clip.id, steps=2, seed=3)
        steps = []
        done = await c.wait(job.id, progress=lambda j: steps.append(j.progress))
        video = await c.job_result(job.id)
        frame = await c.job_frame(job.id, 0)
        return done, steps, video, frame

    done, steps, video, frame = run(server, body)
    assert done.state == "done", refiner.tail()
    assert video.data[4:8] == b"ftyp" and frame.array.ndim == 3


def test_an_unreachable_server_is_a_transport_error():
    async def body(c: AsyncClient):
        assert not await c.ready()
        with pytest.raises(c4g.TransportError):
            await c.models()

    run("http://127.0.0.1:9", body)
