"""The REST contract (``docs/api.md``, ``server/openapi.json``): every operation as a
:class:`~c4g_client._http.Call`, the request it sends and the function that reads its answer.

Both clients send these calls; nothing here waits or touches a socket, so each operation's
meaning is written once. Options the caller leaves out are not sent, so the server's defaults
apply, and option values are passed through as given: the server validates them and says what
to change (``invalid_input``).
"""

from __future__ import annotations

import json
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

import httpx
import numpy as np

from . import _c4gs
from ._approx import SCENE_HEADER, KeyframesLike, PruneLike, approximation_json
from ._camera import CameraLike, TrajectoryLike, camera_json, trajectory_json
from ._errors import FormatError
from ._http import Call, read_json
from ._media import FeatureImage, Image, ScalarImage, Video
from ._records import Clip, Export, Job, Model, Segment, filename_from, fit_error_from, jobs_from
from ._sets import GaussianSet, from_json

#: Formats of the gaussians endpoint (one set per request for ply and splat).
SET_FORMATS = ("json", "binary", "ply", "splat")
#: Formats of the export endpoint (a time range as one file).
RANGE_FORMATS = ("ply_zip", "spz_zip", "splatv")
#: Formats of a single view: RGB PNG, raw f32 depth and alpha, and the lifted features (raw
#: f32 ``[H, W, F]``, or coloured by the clip's PCA basis as an RGB PNG).
VIEW_FORMATS = ("png", "depth", "alpha", "features", "features_pca")


def _drop_none(fields: Mapping[str, Any]) -> Dict[str, Any]:
    return {k: v for k, v in fields.items() if v is not None}


def _header_float(response: httpx.Response, name: str) -> Optional[float]:
    try:
        return float(response.headers[name])
    except (KeyError, ValueError):
        return None


# -- service ----------------------------------------------------------------------------------


def models() -> Call[List[Model]]:
    return Call("GET", ["v1", "models"], lambda r: [Model.from_json(m) for m in read_json(r)["models"]])


def ready() -> Call[Dict[str, Any]]:
    return Call("GET", ["ready"], lambda r: read_json(r) if r.content else {})


# -- clips ------------------------------------------------------------------------------------


def clip(clip_id: str) -> Call[Clip]:
    return Call("GET", ["v1", "clips", clip_id], lambda r: Clip.from_json(read_json(r)))


def clips() -> Call[List[Clip]]:
    return Call("GET", ["v1", "clips"], lambda r: [Clip.from_json(c) for c in read_json(r)["clips"]])


def delete_clip(clip_id: str) -> Call[None]:
    return Call("DELETE", ["v1", "clips", clip_id], lambda r: None)


def context_frame(clip_id: str, index: int) -> Call[Image]:
    return Call("GET", ["v1", "clips", clip_id, "frames", str(int(index))], lambda r: Image(r.content))


def parse_upload(response: httpx.Response) -> Clip:
    """An upload's clip: 201 Created, or 200 OK when the same upload was stored before."""
    return Clip.from_json(read_json(response), created=response.status_code == 201)


# -- Gaussians --------------------------------------------------------------------------------


def gaussians(
    clip_id: str,
    times: Sequence[float],
    *,
    format: str,
    precision: Optional[str] = None,
    quality: Optional[str] = None,
    keyframes: Optional[KeyframesLike] = None,
    prune: Optional[PruneLike] = None,
    features: bool = False,
    scene: Optional[str] = None,
) -> Call[bytes]:
    """The gaussians endpoint's bytes in any of its formats (``json``, ``binary``, ``ply``,
    ``splat``); ``features`` adds each Gaussian's lifted feature vector (JSON ``features``,
    ``C4GS`` version 2, ``.ply`` ``feat_*``; the server refuses it for ``splat``)."""
    body: Dict[str, Any] = {"times": [float(t) for t in times], "format": format}
    if precision is not None:
        body["precision"] = precision
    if features:
        body["features"] = True
    body.update(approximation_json(quality, keyframes, prune, scene))
    return Call("POST", ["v1", "clips", clip_id, "gaussians"], lambda r: r.content, json=body)


def decode(
    clip_id: str,
    times: Sequence[float],
    *,
    precision: str = "f32",
    quality: Optional[str] = None,
    keyframes: Optional[KeyframesLike] = None,
    prune: Optional[PruneLike] = None,
    features: bool = False,
    scene: Optional[str] = None,
) -> Call[List[GaussianSet]]:
    """Sets as arrays, fetched as ``C4GS`` (binary): ``f32`` exact, ``f16`` half the bytes;
    with ``features``, version 2, whose sets carry their lifted features."""
    call = gaussians(
        clip_id,
        times,
        format="binary",
        precision=precision,
        quality=quality,
        keyframes=keyframes,
        prune=prune,
        features=features,
        scene=scene,
    )
    return Call(call.method, call.path, lambda r: _c4gs.decode(r.content), json=call.json)


def decode_json(clip_id: str, times: Sequence[float], **approximation: Any) -> Call[List[GaussianSet]]:
    """Sets as arrays, fetched as JSON (slower; the reference the binary path is tested on)."""
    call = gaussians(clip_id, times, format="json", **approximation)
    return Call(call.method, call.path, lambda r: from_json(read_json(r)), json=call.json)


# -- 4D files ---------------------------------------------------------------------------------


def export(
    clip_id: str,
    format: str,
    *,
    t: Optional[float] = None,
    start: Optional[float] = None,
    end: Optional[float] = None,
    step: Optional[float] = None,
    fps: Optional[float] = None,
    quality: Optional[str] = None,
    keyframes: Optional[KeyframesLike] = None,
    prune: Optional[PruneLike] = None,
    scene: Optional[str] = None,
) -> Call[Export]:
    """A file: a time range as ``ply_zip``, ``spz_zip`` or ``splatv`` (export endpoint), or one
    time as ``ply`` or ``splat`` (the gaussians endpoint, which holds those)."""
    if format in ("ply", "splat"):
        if t is None:
            raise ValueError(f"a .{format} holds one set: give its time t")
        call = gaussians(
            clip_id, [t], format=format, quality=quality, keyframes=keyframes, prune=prune, scene=scene
        )
        return Call(
            call.method,
            call.path,
            lambda r: Export(
                r.content, format, f"{clip_id[:12]}.{format}", 1, None, r.headers.get(SCENE_HEADER)
            ),
            json=call.json,
        )
    if format not in RANGE_FORMATS:
        raise ValueError(f"unknown export format {format!r}: one of {RANGE_FORMATS + ('ply', 'splat')}")
    body = _drop_none({"format": format, "start": start, "end": end, "step": step, "fps": fps})
    body.update(approximation_json(quality, keyframes, prune, scene))

    def parse(r: httpx.Response) -> Export:
        sets = r.headers.get("x-c4g-sets")
        return Export(
            r.content,
            format,
            filename_from(r.headers.get("content-disposition")),
            int(sets) if sets and sets.isdigit() else None,
            fit_error_from(r.headers.get("x-c4g-fit-position-error")),
            r.headers.get(SCENE_HEADER),
        )

    return Call("POST", ["v1", "clips", clip_id, "export"], parse, json=body)


# -- the compact 4D stream --------------------------------------------------------------------


def stream(
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
    scene: Optional[str] = None,
) -> Call[None]:
    """The C4GV stream's request; its chunked body is read by the clients as it arrives."""
    body = _drop_none(
        {
            "start": start,
            "end": end,
            "step": step,
            "fps": fps,
            "position_error": position_error,
            "keyframe_interval": keyframe_interval,
        }
    )
    body.update(approximation_json(quality, keyframes, prune, scene))
    return Call("POST", ["v1", "clips", clip_id, "stream"], lambda r: None, json=body)


# -- rendering --------------------------------------------------------------------------------


def render(
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
    scene: Optional[str] = None,
) -> Call[Union[Image, ScalarImage, FeatureImage]]:
    """One view: a PNG :class:`Image` (``png``, ``features_pca``), raw ``f32`` ``depth`` /
    ``alpha`` as a :class:`ScalarImage`, or raw ``f32`` ``features`` as a
    :class:`FeatureImage`."""
    if format not in VIEW_FORMATS:
        raise ValueError(f"unknown render format {format!r}: one of {VIEW_FORMATS}")
    body = _drop_none(
        {
            "t": t,
            "camera": camera_json(camera),
            "width": width,
            "height": height,
            "background": [float(v) for v in background] if background is not None else None,
            "format": format,
        }
    )
    body.update(approximation_json(quality, None, prune, scene))

    def parse(r: httpx.Response) -> Union[Image, ScalarImage, FeatureImage]:
        time = _header_float(r, "x-c4g-time")
        served = r.headers.get(SCENE_HEADER)
        if format in ("png", "features_pca"):
            return Image(r.content, time, served)
        w, h = int(r.headers.get("x-c4g-width", 0)), int(r.headers.get("x-c4g-height", 0))
        if format == "features":
            return _feature_image(r, w, h, time, served)
        if len(r.content) != 4 * w * h:
            raise FormatError(f"a {w}x{h} {format} render is {4 * w * h} bytes; got {len(r.content)}")
        return ScalarImage(
            np.frombuffer(r.content, dtype="<f4").reshape(h, w).astype(np.float32), format, time, served
        )

    return Call("POST", ["v1", "clips", clip_id, "render"], parse, json=body)


def _feature_image(
    r: httpx.Response, w: int, h: int, time: Optional[float], scene: Optional[str]
) -> FeatureImage:
    """A raw feature render: ``X-C4G-Channels`` floats a pixel, checked against the length."""
    channels = r.headers.get("x-c4g-channels", "")
    if not channels.isdigit() or int(channels) == 0:
        raise FormatError(f"a features render says its channels in X-C4G-Channels; got {channels!r}")
    f = int(channels)
    if len(r.content) != 4 * w * h * f:
        raise FormatError(
            f"a {w}x{h} features render of {f} channels is {4 * w * h * f} bytes; got {len(r.content)}"
        )
    return FeatureImage(
        np.frombuffer(r.content, dtype="<f4").reshape(h, w, f).astype(np.float32), time, scene
    )


def render_video(
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
    scene: Optional[str] = None,
) -> Call[Video]:
    """A video along a preset path (around ``camera``) or explicit ``cameras``, as MP4."""
    if (trajectory is None) == (cameras is None):
        raise ValueError("a video takes a trajectory preset or cameras (one of them)")
    body = _drop_none(
        {
            "trajectory": trajectory_json(trajectory),
            "cameras": [camera_json(c) for c in cameras] if cameras is not None else None,
            "camera": camera_json(camera),
            "frames": frames,
            "start": start,
            "end": end,
            "fps": fps,
            "width": width,
            "height": height,
            "background": [float(v) for v in background] if background is not None else None,
            "format": "mp4",
        }
    )
    body.update(approximation_json(quality, keyframes, prune, scene))
    return Call(
        "POST",
        ["v1", "clips", clip_id, "render"],
        lambda r: Video(r.content, r.headers.get("content-type", "video/mp4"), r.headers.get(SCENE_HEADER)),
        json=body,
    )


# -- segments ---------------------------------------------------------------------------------


ClickLike = Union[Sequence[float], Mapping[str, float]]


def segment(
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
) -> Call[Segment]:
    """The Gaussians whose lifted feature is like a clicked pixel's (``click``: ``(t, x, y)``
    or ``{"t": .., "x": .., "y": ..}``) or like ``feature`` (compared at ``t``), and their
    masks at ``times``. A click and a feature together are sent as given: the server says
    which to keep."""
    if click is not None and not isinstance(click, Mapping):
        at, x, y = click
        click = {"t": float(at), "x": float(x), "y": float(y)}
    body = _drop_none(
        {
            "click": dict(click) if click is not None else None,
            "feature": (
                [float(v) for v in np.asarray(feature, dtype=np.float32).reshape(-1)]
                if feature is not None
                else None
            ),
            "t": t,
            "threshold": threshold,
            "times": [float(x) for x in times] if times is not None else None,
            "camera": camera_json(camera),
            "width": width,
            "height": height,
        }
    )
    return Call(
        "POST", ["v1", "clips", clip_id, "segment"], lambda r: Segment.from_json(read_json(r)), json=body
    )


# -- refinement -------------------------------------------------------------------------------


def refine(clip_id: str, request: Mapping[str, Any]) -> Call[Job]:
    """Queue a refinement; ``request`` holds docs/api.md's fields (presets and cameras may be
    this package's classes)."""
    body: Dict[str, Any] = {}
    for name, value in request.items():
        if value is None:
            continue
        if name == "trajectory":
            value = trajectory_json(value)
        elif name == "camera":
            value = camera_json(value)
        elif name == "cameras":
            value = [camera_json(c) for c in value]
        elif name in ("text_embedding", "negative_embedding"):
            value = [float(v) for v in np.asarray(value, dtype=np.float32).reshape(-1)]
        body[name] = value

    def parse(r: httpx.Response) -> Job:
        if r.status_code != 202:
            raise FormatError(f"a refinement is answered 202 Accepted, not {r.status_code}")
        return Job.from_json(read_json(r))

    return Call("POST", ["v1", "clips", clip_id, "refine"], parse, json=body)


#: The fields of a fit request (docs/api.md, Fitting); the preset's value stands for one left out.
FIT_FIELDS = (
    "preset",
    "steps",
    "resolution",
    "max_gaussians",
    "keyframe_every",
    "holdout_every",
    "refine_cameras",
    "time_budget_s",
    "seed",
    "max_frames",
)


def fit(clip_id: str, request: Mapping[str, Any]) -> Call[Job]:
    """Queue a fit of the clip's scene to its own frames; ``request`` holds docs/api.md's
    fields (those left ``None`` are not sent: the preset's values stand for them)."""
    body = _drop_none(request)

    def parse(r: httpx.Response) -> Job:
        if r.status_code != 202:
            raise FormatError(f"a fit is answered 202 Accepted, not {r.status_code}")
        return Job.from_json(read_json(r))

    return Call("POST", ["v1", "clips", clip_id, "fit"], parse, json=body)


def job(job_id: str) -> Call[Job]:
    return Call("GET", ["v1", "jobs", job_id], lambda r: Job.from_json(read_json(r)))


def jobs() -> Call[List[Job]]:
    return Call("GET", ["v1", "jobs"], lambda r: jobs_from(read_json(r)))


def cancel(job_id: str) -> Call[Job]:
    return Call("POST", ["v1", "jobs", job_id, "cancel"], lambda r: Job.from_json(read_json(r)))


def job_events(job_id: str) -> Call[None]:
    return Call(
        "GET", ["v1", "jobs", job_id, "events"], lambda r: None, headers={"accept": "text/event-stream"}
    )


def job_result(job_id: str) -> Call[Video]:
    return Call(
        "GET",
        ["v1", "jobs", job_id, "result"],
        lambda r: Video(r.content, r.headers.get("content-type", "video/mp4")),
    )


def job_frame(job_id: str, frame: int) -> Call[Image]:
    return Call(
        "GET", ["v1", "jobs", job_id, "result"], lambda r: Image(r.content), params={"frame": str(int(frame))}
    )


def job_from_event(data: str) -> Job:
    """A job record from a ``job`` event's data."""
    try:
        return Job.from_json(json.loads(data))
    except ValueError as e:
        raise FormatError(f"a job event that is not a job record ({e})") from None


def sets_header(response: httpx.Response) -> Optional[int]:
    """``X-C4G-Sets``: how many sets a stream or export holds."""
    value = response.headers.get("x-c4g-sets")
    return int(value) if value and value.isdigit() else None
