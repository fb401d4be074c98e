"""The blocking client: :class:`Client`, one method per operation of the service.

Each method builds its request from ``_endpoints.py`` and sends it with an ``httpx.Client``
(a connection pool, so keep one client and reuse it; close it, or use ``with``). gRPC calls go
over one channel, opened by the first of them and closed with the client. Errors the
server answers raise the kind's exception (:mod:`c4g_client` lists them); a connection that
fails raises :class:`~c4g_client.TransportError`.
"""

from __future__ import annotations

import numbers
import os
from typing import Any, Iterator, List, Optional, Sequence, TypeVar, Union, overload

import httpx

from . import _endpoints as ep
from . import _grpc, _upload
from ._approx import KeyframesLike, PruneLike, Scene
from ._camera import CameraLike, TrajectoryLike
from ._endpoints import ClickLike
from ._errors import StreamInterrupted, TransportError
from ._http import DEFAULT_TIMEOUT, Call, auth_headers, error_from, normalise_base_url
from ._media import FeatureImage, Image, ScalarImage, Video
from ._records import Clip, Export, Job, Model, PathLike, Segment
from ._sets import GaussianSet
from ._stream import JobCallback, SetStream, job_events
from ._upload import Progress, UploadSource

T = TypeVar("T")

#: Where a client connects when given no URL: ``$C4G_URL``, else the server's default port.
DEFAULT_URL = "http://127.0.0.1:8080"

Times = Union[float, Sequence[float]]


def default_url(base_url: Optional[str]) -> str:
    return normalise_base_url(base_url or os.environ.get("C4G_URL") or DEFAULT_URL)


def default_key(api_key: Optional[str]) -> Optional[str]:
    return api_key if api_key is not None else os.environ.get("C4G_API_KEY") or None


def times_of(t: Times) -> List[float]:
    """One time or several as the list the API takes."""
    if isinstance(t, numbers.Real):
        return [float(t)]
    return [float(x) for x in t]  # type: ignore[union-attr]


class Client:
    """A connection to one c4g server (``base_url``, default ``$C4G_URL`` or
    ``http://127.0.0.1:8080``), sending ``api_key`` (default ``$C4G_API_KEY``) as a bearer
    token. Times are seconds of media time; a time outside the clip's context span raises
    :class:`~c4g_client.InvalidInput`."""

    def __init__(
        self,
        base_url: Optional[str] = None,
        api_key: Optional[str] = None,
        *,
        timeout: Any = DEFAULT_TIMEOUT,
        transport: Optional[httpx.BaseTransport] = None,
    ) -> None:
        self.base_url = default_url(base_url)
        self._api_key = default_key(api_key)
        self._http = httpx.Client(headers=auth_headers(self._api_key), timeout=timeout, transport=transport)
        self._grpc_channel: Any = None

    def close(self) -> None:
        """Closes the connection pool and the gRPC channel (ending any gRPC stream still open)."""
        self._http.close()
        if self._grpc_channel is not None:
            self._grpc_channel.close()
            self._grpc_channel = None

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Client({self.base_url!r})"

    # -- plumbing ---------------------------------------------------------------------------

    def _send(self, call: Call[Any], *, stream: bool = False) -> httpx.Response:
        request = call.request(self._http, self.base_url)
        try:
            response = self._http.send(request, stream=stream)
        except httpx.TransportError as e:
            raise TransportError(f"{call.method} {request.url}: {e}") from e
        if response.is_error:
            response.read()
            response.close()
            raise error_from(response)
        return response

    def _run(self, call: Call[T]) -> T:
        return call.parse(self._send(call))

    def _channel(self) -> Any:
        """The client's gRPC channel, opened by the first gRPC call: later calls reuse it."""
        if self._http.is_closed:
            raise RuntimeError("the client is closed: make a new one")
        if self._grpc_channel is None:
            self._grpc_channel = _grpc.open_channel(self.base_url)
        return self._grpc_channel

    # -- service ----------------------------------------------------------------------------

    def models(self) -> List[Model]:
        """The served model package (``GET /v1/models``)."""
        return self._run(ep.models())

    def ready(self) -> bool:
        """Whether the model is loaded and the server takes requests (``GET /ready``)."""
        try:
            return self._http.get(self.base_url + "/ready").status_code == 200
        except httpx.TransportError:
            return False

    # -- clips ------------------------------------------------------------------------------

    def upload(
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
        """Uploads a clip and waits until the server has encoded it.

        ``source``: a video or image-archive path, a folder of PNG/JPEG frames (name order),
        an image path or a list of them, ``bytes``, or a list of ``(H, W, 3)`` ``uint8``
        arrays. ``times`` gives
        image frames their timestamps (seconds, increasing), else ``fps`` (server default 10).
        ``progress(sent, total)`` is called as body bytes go out. The same bytes with the same
        options give the same clip (``created`` is False then) and are not encoded again.
        """
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
            content=body.chunks(progress),
        )
        return self._run(call)

    def clip(self, clip_id: str) -> Clip:
        """Describes a clip."""
        return self._run(ep.clip(clip_id))

    def clips(self) -> List[Clip]:
        """Every clip, oldest first."""
        return self._run(ep.clips())

    def delete_clip(self, clip_id: str) -> None:
        """Deletes a clip: its record, features and frames."""
        self._run(ep.delete_clip(clip_id))

    def context_frame(self, clip_id: str, index: int) -> Image:
        """Context frame ``index`` (in time order) as the model saw it, before preprocessing."""
        return self._run(ep.context_frame(clip_id, index))

    # -- Gaussians --------------------------------------------------------------------------

    @overload
    def decode(
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
    def decode(
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

    def decode(
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
        """The Gaussians at one time (a :class:`GaussianSet`) or several (a list, in the order
        given), as NumPy arrays in gsplat's conventions. ``precision="f16"`` halves the bytes
        on the wire (values rounded to the nearest half); ``quality``, ``keyframes`` and
        ``prune`` trade accuracy for speed (docs/api.md). ``features=True`` adds each
        Gaussian's lifted feature vector (``.features``, ``(N, F)``), on a package with a
        feature decoder (:class:`~c4g_client.Unsupported` otherwise). ``scene`` picks the
        scene: ``"auto"`` (the server's default: the clip's fitted scene when it has one and
        nothing above asks for an approximation or features), ``"feed-forward"`` or
        ``"fitted"`` (:class:`~c4g_client.NotFound` when the clip has none; every method that
        takes sets takes it alike)."""
        sets = self._run(
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

    def gaussians_raw(
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
        """The gaussians endpoint's bytes as the server sent them (``json``, ``binary``,
        ``ply``, ``splat``); ``features`` as for :meth:`decode` (``C4GS`` version 2, ``.ply``
        ``feat_*`` properties; ``splat`` has no room for them)."""
        return self._run(
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

    def export(
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
        """A file other viewers open: ``ply_zip``, ``spz_zip`` or ``splatv`` over a time range
        (default the whole span at the clip's frame rate), or ``ply`` / ``splat`` of one time
        ``t``. Written to ``path`` too when given."""
        export = self._run(
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

    def stream(
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
    ) -> SetStream:
        """The sets over a time range as the compact 4D stream (C4GV), decoded as they
        arrive: iterate it (or use ``with``). Positions are within ``position_error`` (default
        1e-3 scene units); scales, rotations, opacities and colours within 4.9e-4."""
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
        return SetStream(self._send(call, stream=True))

    def grpc_stream(
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
    ) -> _grpc.GrpcSetStream:
        """The sets over a time range over gRPC (``StreamGaussians``; the ``grpc`` extra):
        packed ``f32`` / ``f16`` sets, or with ``compact=position_error`` the C4GV stream."""
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
        return _grpc.GrpcSetStream(self._channel(), self._api_key, request, compact is not None)

    @overload
    def grpc_decode(
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
    def grpc_decode(
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

    def grpc_decode(
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
        """:meth:`decode` over gRPC (``Decode``; the ``grpc`` extra): the same sets, with the
        lifted features when ``features=True`` (``GaussianSet.features`` of the message)."""
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
        sets = _grpc.decode(self._channel(), self._api_key, request)
        return sets[0] if isinstance(t, numbers.Real) else sets

    # -- rendering --------------------------------------------------------------------------

    def render(
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
        """One view at time ``t`` (default the span's start) from ``camera`` (default the first
        context camera): ``png`` gives an :class:`Image` (``.array`` is ``(H, W, 3)`` uint8),
        ``depth`` or ``alpha`` a :class:`ScalarImage` of ``float32``. On a package with a
        feature decoder, ``features`` gives a :class:`FeatureImage` (``(H, W, F)`` ``float32``:
        each pixel its Gaussians' features composited like colour, no background) and
        ``features_pca`` an :class:`Image` (the features coloured by the clip's PCA basis,
        which is the same at every time and from every camera). Each says the scene that
        rendered it (``.scene``: ``feed-forward`` or ``fitted``; ``scene=`` asks for one)."""
        return self._run(
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

    def render_video(
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
        """An MP4 along a preset (:class:`Orbit`, :class:`Spiral`, :class:`Dolly`) or explicit
        ``cameras``, over ``start``..``end``; written to ``path`` too when given."""
        video = self._run(
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

    # -- segments ---------------------------------------------------------------------------

    def segment(
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
        """The Gaussians whose lifted feature is like what pixel ``(x, y)`` shows at time ``t``
        (``click=(t, x, y)``, in ``camera`` at ``width`` x ``height``) or like ``feature`` (F
        numbers, compared at ``t``, default the first context time): every Gaussian whose
        feature's cosine similarity reaches ``threshold`` (server default 0.8). The answer holds
        them and a :class:`Mask` per time of ``times`` (default the context times; the
        selection is made once, so the masks follow the same Gaussians wherever they move). A
        package without a feature decoder raises :class:`~c4g_client.Unsupported`."""
        return self._run(
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

    # -- fitting ----------------------------------------------------------------------------

    def fit(
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
        """Queues a fit of the clip's scene to its own frames (a ``c4g-fitter`` worker runs
        it); returns the queued :class:`Job` (``kind`` ``fit``). ``preset`` is ``"fast"``,
        ``"default"`` (the server's) or ``"best"``; the other fields override its values
        (docs/api.md, Fitting); ``extra`` passes fields this version does not name. Follow it
        with :meth:`wait` or :meth:`follow` (its progress has ``loss``, ``holdout_psnr``,
        ``gaussians``, ``elapsed_s``); once it is done, :meth:`clip` lists the fitted scene
        (:attr:`Clip.fitted <c4g_client.Clip.fitted>`) and requests serve it by default."""
        fields = dict(locals())
        for name in ("self", "clip_id", "extra"):
            fields.pop(name)
        fields.update(extra)
        return self._run(ep.fit(clip_id, fields))

    # -- refinement -------------------------------------------------------------------------

    def refine(
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
        """Queues a refinement of novel views along a path (a ``c4g-refiner`` worker runs
        it); returns the queued :class:`Job`. Fields as docs/api.md's; ``extra`` passes fields
        this version does not name."""
        fields = dict(locals())
        for name in ("self", "clip_id", "extra"):
            fields.pop(name)
        fields.update(extra)
        return self._run(ep.refine(clip_id, fields))

    def job(self, job_id: str) -> Job:
        """A job's record now."""
        return self._run(ep.job(job_id))

    def jobs(self) -> List[Job]:
        """Every job, oldest first."""
        return self._run(ep.jobs())

    def cancel(self, job_id: str) -> Job:
        """Cancels a job: a queued one at once, a running one at its worker's next step."""
        return self._run(ep.cancel(job_id))

    def follow(self, job_id: str, progress: Optional[JobCallback] = None) -> Iterator[Job]:
        """The job's record now and on every change (server-sent events), ending after a
        terminal state; ``progress(job)`` is called with each."""
        return job_events(self._send(ep.job_events(job_id), stream=True), progress)

    def wait(self, job_id: str, progress: Optional[JobCallback] = None, *, reconnects: int = 5) -> Job:
        """Follows a job until it ends and returns its last record (reconnecting when the
        event stream drops)."""
        for attempt in range(reconnects + 1):
            try:
                last: Optional[Job] = None
                for job in self.follow(job_id, progress):
                    last = job
                assert last is not None
                return last
            except (StreamInterrupted, TransportError):
                if attempt == reconnects:
                    raise
        raise AssertionError("unreachable")

    def job_result(self, job_id: str, path: Optional[PathLike] = None) -> Video:
        """The refined novel views as MP4 (once the job is done); written to ``path`` too."""
        video = self._run(ep.job_result(job_id))
        if path is not None:
            video.save(path)
        return video

    def job_frame(self, job_id: str, frame: int) -> Image:
        """One refined frame (``frame`` below the job's ``result_frames``) as an image."""
        return self._run(ep.job_frame(job_id, frame))
