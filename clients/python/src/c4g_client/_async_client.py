"""The asyncio client: :class:`AsyncClient`, the same operations as
:class:`~c4g_client.Client` with the same arguments and results, awaited.

It sends the same :class:`~c4g_client._http.Call` values as the blocking client with an
``httpx.AsyncClient``, and its gRPC calls over one ``grpc.aio`` channel, opened by the first of
them (in the event loop that makes it, which it is bound to) and closed by :meth:`aclose`;
streams are ``async for`` iterators. Methods are documented once, on
:class:`~c4g_client.Client`.
"""

from __future__ import annotations

import numbers
from typing import Any, AsyncIterator, List, Optional, Sequence, TypeVar, Union, overload

import httpx

from . import _endpoints as ep
from . import _grpc, _upload
from ._approx import KeyframesLike, PruneLike, Scene
from ._camera import CameraLike, TrajectoryLike
from ._client import Times, default_key, default_url, times_of
from ._endpoints import ClickLike
from ._errors import StreamInterrupted, TransportError
from ._http import DEFAULT_TIMEOUT, Call, auth_headers, error_from
from ._media import FeatureImage, Image, ScalarImage, Video
from ._records import Clip, Export, Job, Model, PathLike, Segment
from ._sets import GaussianSet
from ._stream import AsyncSetStream, JobCallback, ajob_events
from ._upload import Progress, UploadSource

T = TypeVar("T")


class AsyncClient:
    """A connection to one c4g server for asyncio code; see :class:`~c4g_client.Client`."""

    def __init__(
        self,
        base_url: Optional[str] = None,
        api_key: Optional[str] = None,
        *,
        timeout: Any = DEFAULT_TIMEOUT,
        transport: Optional[httpx.AsyncBaseTransport] = None,
    ) -> None:
        self.base_url = default_url(base_url)
        self._api_key = default_key(api_key)
        self._http = httpx.AsyncClient(
            headers=auth_headers(self._api_key), timeout=timeout, transport=transport
        )
        self._grpc_channel: Any = None

    async def aclose(self) -> None:
        await self._http.aclose()
        if self._grpc_channel is not None:
            await self._grpc_channel.close()
            self._grpc_channel = None

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    def __repr__(self) -> str:
        return f"AsyncClient({self.base_url!r})"

    def _channel(self) -> Any:
        """The client's ``grpc.aio`` channel, opened by the first gRPC call: later calls reuse it."""
        if self._http.is_closed:
            raise RuntimeError("the client is closed: make a new one")
        if self._grpc_channel is None:
            self._grpc_channel = _grpc.open_channel(self.base_url, aio=True)
        return self._grpc_channel

    async def _send(self, call: Call[Any], *, stream: bool = False) -> httpx.Response:
        request = call.request(self._http, self.base_url)
        try:
            response = await self._http.send(request, stream=stream)
        except httpx.TransportError as e:
            raise TransportError(f"{call.method} {request.url}: {e}") from e
        if response.is_error:
            await response.aread()
            await response.aclose()
            raise error_from(response)
        return response

    async def _run(self, call: Call[T]) -> T:
        return call.parse(await self._send(call))

    async def models(self) -> List[Model]:
        return await self._run(ep.models())

    async def ready(self) -> bool:
        try:
            return (await self._http.get(self.base_url + "/ready")).status_code == 200
        except httpx.TransportError:
            return False

    async def upload(
        self,
        source: UploadSource,
        *,
        fps: Optional[float] = None,
        times: Optional[Sequence[float]] = None,
        max_frames: Optional[int] = None,
        stride: Optional[int] = None,
        start: Optional[float] = None,
        end: Optional[float] = None,
        content_type: Optional[str] = None,
        progress: Optional[Progress] = None,
    ) -> Clip:
        pairs = _upload.options(
            fps=fps, times=times, max_frames=max_frames, stride=stride, start=start, end=end
        )
        body = _upload.body_for(source, pairs, content_type)
        call = Call(
            "POST",
            ["v1", "clips"],
            ep.parse_upload,
            params=body.query or None,
            headers={"content-type": body.content_type, "content-length": str(body.total)},
            content=body.achunks(progress),
        )
        return await self._run(call)

    async def clip(self, clip_id: str) -> Clip:
        return await self._run(ep.clip(clip_id))

    async def clips(self) -> List[Clip]:
        return await self._run(ep.clips())

    async def delete_clip(self, clip_id: str) -> None:
        await self._run(ep.delete_clip(clip_id))

    async def context_frame(self, clip_id: str, index: int) -> Image:
        return await self._run(ep.context_frame(clip_id, index))

    @overload
    async def decode(
        self,
        clip_id: str,
        t: float,
        *,
        precision: str = ...,
        quality: Optional[str] = ...,
        keyframes: Optional[KeyframesLike] = ...,
        prune: Optional[PruneLike] = ...,
        scene: Optional[Scene] = ...,
        features: bool = ...,
    ) -> GaussianSet: ...

    @overload
    async def decode(
        self,
        clip_id: str,
        t: Sequence[float],
        *,
        precision: str = ...,
        quality: Optional[str] = ...,
        keyframes: Optional[KeyframesLike] = ...,
        prune: Optional[PruneLike] = ...,
        scene: Optional[Scene] = ...,
        features: bool = ...,
    ) -> List[GaussianSet]: ...

    async def decode(
        self,
        clip_id: str,
        t: Times,
        *,
        precision: str = "f32",
        quality: Optional[str] = None,
        keyframes: Optional[KeyframesLike] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
        features: bool = False,
    ) -> Union[GaussianSet, List[GaussianSet]]:
        sets = await self._run(
            ep.decode(
                clip_id,
                times_of(t),
                precision=precision,
                quality=quality,
                keyframes=keyframes,
                prune=prune,
                scene=scene,
                features=features,
            )
        )
        return sets[0] if isinstance(t, numbers.Real) else sets

    async def gaussians_raw(
        self,
        clip_id: str,
        t: Times,
        *,
        format: str = "json",
        precision: Optional[str] = None,
        quality: Optional[str] = None,
        keyframes: Optional[KeyframesLike] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
        features: bool = False,
    ) -> bytes:
        return await self._run(
            ep.gaussians(
                clip_id,
                times_of(t),
                format=format,
                precision=precision,
                quality=quality,
                keyframes=keyframes,
                prune=prune,
                scene=scene,
                features=features,
            )
        )

    async def export(
        self,
        clip_id: str,
        format: str,
        *,
        path: Optional[PathLike] = None,
        t: Optional[float] = None,
        start: Optional[float] = None,
        end: Optional[float] = None,
        step: Optional[float] = None,
        fps: Optional[float] = None,
        quality: Optional[str] = None,
        keyframes: Optional[KeyframesLike] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
    ) -> Export:
        export = await self._run(
            ep.export(
                clip_id,
                format,
                t=t,
                start=start,
                end=end,
                step=step,
                fps=fps,
                quality=quality,
                keyframes=keyframes,
                prune=prune,
                scene=scene,
            )
        )
        if path is not None:
            export.save(path)
        return export

    async def stream(
        self,
        clip_id: str,
        *,
        start: Optional[float] = None,
        end: Optional[float] = None,
        step: Optional[float] = None,
        fps: Optional[float] = None,
        position_error: Optional[float] = None,
        keyframe_interval: Optional[int] = None,
        quality: Optional[str] = None,
        keyframes: Optional[KeyframesLike] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
    ) -> AsyncSetStream:
        call = ep.stream(
            clip_id,
            start=start,
            end=end,
            step=step,
            fps=fps,
            position_error=position_error,
            keyframe_interval=keyframe_interval,
            quality=quality,
            keyframes=keyframes,
            prune=prune,
            scene=scene,
        )
        return AsyncSetStream(await self._send(call, stream=True))

    async def grpc_stream(
        self,
        clip_id: str,
        *,
        start: Optional[float] = None,
        end: Optional[float] = None,
        step: Optional[float] = None,
        fps: Optional[float] = None,
        precision: str = "f32",
        compact: Optional[float] = None,
        keyframe_interval: int = 0,
        quality: Optional[str] = None,
        keyframes: Optional[KeyframesLike] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
    ) -> _grpc.AsyncGrpcSetStream:
        request = _grpc.stream_request(
            clip_id,
            start=start,
            end=end,
            step=step,
            fps=fps,
            precision=precision,
            quality=quality,
            keyframes=keyframes,
            prune=prune,
            scene=scene,
            compact=None if compact is None else (compact, keyframe_interval),
        )
        return await _grpc.AsyncGrpcSetStream(
            self._channel(), self._api_key, request, compact is not None
        ).start()

    @overload
    async def grpc_decode(
        self,
        clip_id: str,
        t: float,
        *,
        precision: str = ...,
        quality: Optional[str] = ...,
        keyframes: Optional[KeyframesLike] = ...,
        prune: Optional[PruneLike] = ...,
        scene: Optional[Scene] = ...,
        features: bool = ...,
    ) -> GaussianSet: ...

    @overload
    async def grpc_decode(
        self,
        clip_id: str,
        t: Sequence[float],
        *,
        precision: str = ...,
        quality: Optional[str] = ...,
        keyframes: Optional[KeyframesLike] = ...,
        prune: Optional[PruneLike] = ...,
        scene: Optional[Scene] = ...,
        features: bool = ...,
    ) -> List[GaussianSet]: ...

    async def grpc_decode(
        self,
        clip_id: str,
        t: Times,
        *,
        precision: str = "f32",
        quality: Optional[str] = None,
        keyframes: Optional[KeyframesLike] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
        features: bool = False,
    ) -> Union[GaussianSet, List[GaussianSet]]:
        request = _grpc.decode_request(
            clip_id,
            times_of(t),
            precision=precision,
            quality=quality,
            keyframes=keyframes,
            prune=prune,
            scene=scene,
            features=features,
        )
        sets = await _grpc.adecode(self._channel(), self._api_key, request)
        return sets[0] if isinstance(t, numbers.Real) else sets

    async def render(
        self,
        clip_id: str,
        t: Optional[float] = None,
        *,
        camera: Optional[CameraLike] = None,
        width: Optional[int] = None,
        height: Optional[int] = None,
        background: Optional[Sequence[float]] = None,
        format: str = "png",
        quality: Optional[str] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
    ) -> Union[Image, ScalarImage, FeatureImage]:
        return await self._run(
            ep.render(
                clip_id,
                t,
                camera=camera,
                width=width,
                height=height,
                background=background,
                format=format,
                quality=quality,
                prune=prune,
                scene=scene,
            )
        )

    async def render_video(
        self,
        clip_id: str,
        trajectory: Optional[TrajectoryLike] = None,
        *,
        cameras: Optional[Sequence[CameraLike]] = None,
        camera: Optional[CameraLike] = None,
        frames: Optional[int] = None,
        start: Optional[float] = None,
        end: Optional[float] = None,
        fps: Optional[float] = None,
        width: Optional[int] = None,
        height: Optional[int] = None,
        background: Optional[Sequence[float]] = None,
        quality: Optional[str] = None,
        keyframes: Optional[KeyframesLike] = None,
        prune: Optional[PruneLike] = None,
        scene: Optional[Scene] = None,
        path: Optional[PathLike] = None,
    ) -> Video:
        video = await self._run(
            ep.render_video(
                clip_id,
                trajectory,
                cameras=cameras,
                camera=camera,
                frames=frames,
                start=start,
                end=end,
                fps=fps,
                width=width,
                height=height,
                background=background,
                quality=quality,
                keyframes=keyframes,
                prune=prune,
                scene=scene,
            )
        )
        if path is not None:
            video.save(path)
        return video

    async def segment(
        self,
        clip_id: str,
        *,
        click: Optional[ClickLike] = None,
        feature: Any = None,
        t: Optional[float] = None,
        threshold: Optional[float] = None,
        times: Optional[Sequence[float]] = None,
        camera: Optional[CameraLike] = None,
        width: Optional[int] = None,
        height: Optional[int] = None,
    ) -> Segment:
        return await self._run(
            ep.segment(
                clip_id,
                click=click,
                feature=feature,
                t=t,
                threshold=threshold,
                times=times,
                camera=camera,
                width=width,
                height=height,
            )
        )

    async def fit(
        self,
        clip_id: str,
        *,
        preset: Optional[str] = None,
        steps: Optional[int] = None,
        resolution: Optional[int] = None,
        max_gaussians: Optional[int] = None,
        keyframe_every: Optional[int] = None,
        holdout_every: Optional[int] = None,
        refine_cameras: Optional[bool] = None,
        time_budget_s: Optional[float] = None,
        seed: Optional[int] = None,
        max_frames: Optional[int] = None,
        **extra: Any,
    ) -> Job:
        fields = dict(locals())
        for name in ("self", "clip_id", "extra"):
            fields.pop(name)
        fields.update(extra)
        return await self._run(ep.fit(clip_id, fields))

    async def refine(
        self,
        clip_id: str,
        *,
        trajectory: Optional[TrajectoryLike] = None,
        cameras: Optional[Sequence[CameraLike]] = None,
        camera: Optional[CameraLike] = None,
        start: Optional[float] = None,
        end: Optional[float] = None,
        context_frames: Optional[int] = None,
        caption: Optional[str] = None,
        negative_prompt: Optional[str] = None,
        text_embedding: Any = None,
        text_tokens: Optional[int] = None,
        negative_embedding: Any = None,
        steps: Optional[int] = None,
        shift: Optional[float] = None,
        guidance: Optional[float] = None,
        sampler: Optional[str] = None,
        seed: Optional[int] = None,
        control_scale: Optional[float] = None,
        fps: Optional[float] = None,
        **extra: Any,
    ) -> Job:
        fields = dict(locals())
        for name in ("self", "clip_id", "extra"):
            fields.pop(name)
        fields.update(extra)
        return await self._run(ep.refine(clip_id, fields))

    async def job(self, job_id: str) -> Job:
        return await self._run(ep.job(job_id))

    async def jobs(self) -> List[Job]:
        return await self._run(ep.jobs())

    async def cancel(self, job_id: str) -> Job:
        return await self._run(ep.cancel(job_id))

    async def follow(self, job_id: str, progress: Optional[JobCallback] = None) -> AsyncIterator[Job]:
        """``async for job in await client.follow(job_id)``: see :meth:`Client.follow`."""
        return ajob_events(await self._send(ep.job_events(job_id), stream=True), progress)

    async def wait(self, job_id: str, progress: Optional[JobCallback] = None, *, reconnects: int = 5) -> Job:
        for attempt in range(reconnects + 1):
            try:
                last: Optional[Job] = None
                async for job in await self.follow(job_id, progress):
                    last = job
                assert last is not None
                return last
            except (StreamInterrupted, TransportError):
                if attempt == reconnects:
                    raise
        raise AssertionError("unreachable")

    async def job_result(self, job_id: str, path: Optional[PathLike] = None) -> Video:
        video = await self._run(ep.job_result(job_id))
        if path is not None:
            video.save(path)
        return video

    async def job_frame(self, job_id: str, frame: int) -> Image:
        return await self._run(ep.job_frame(job_id, frame))
