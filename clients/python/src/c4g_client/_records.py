"""The server's records as typed values: a :class:`Clip` (an upload, with its
:class:`FittedSummary` once a fit made one), the served :class:`Model`, a :class:`Job` (a
refinement or a fit), an :class:`Export` file, and a :class:`Segment` (the Gaussians a lifted
feature selects, with a :class:`Mask` per time).

Each keeps the JSON it came from in ``raw``, so a field a newer server adds is still there
before this package names it.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Tuple, Union

import numpy as np

from ._errors import FormatError

PathLike = Union[str, "os.PathLike[str]"]

TERMINAL_STATES = ("done", "failed", "cancelled")


@dataclass(frozen=True)
class ClipSource:
    """What was uploaded: ``video`` or ``images``, its frames, size, duration and rate, and
    what reading it skipped or changed (``warnings``)."""

    kind: str
    frames: int
    width: int
    height: int
    duration: float
    fps: float
    warnings: Tuple[str, ...] = ()


@dataclass(frozen=True)
class FittedSummary:
    """A clip's fitted scene as its record lists it (``docs/api.md``, Fitting): what a fit made
    of the clip's own frames, which requests serve by default. ``holdout_psnr`` is the mean PSNR
    (dB) of the frames the fit never trained on (``holdout_frames``, indices among its
    ``frames``) at their input cameras, beside ``holdout_psnr_feed_forward``, the model's answer
    on the same frames; both ``None`` when nothing was held out."""

    job_id: str
    preset: str
    gaussians: int
    static_gaussians: int
    keyframes: Tuple[float, ...]
    steps: int
    seconds: float
    frames: int
    resolution: Tuple[int, int]
    holdout_frames: Tuple[int, ...]
    holdout_times: Tuple[float, ...]
    holdout_psnr: Optional[float]
    holdout_psnr_feed_forward: Optional[float]
    train_psnr: Optional[float]
    stopped_early: bool
    created_at: int
    #: What a person should know about the fit beyond its numbers (a camera that probably moved).
    notes: Tuple[str, ...]
    raw: Dict[str, Any] = field(repr=False, compare=False)

    @property
    def holdout_gain(self) -> Optional[float]:
        """What fitting gained on the held-out frames, dB (``None`` without them)."""
        if self.holdout_psnr is None or self.holdout_psnr_feed_forward is None:
            return None
        return self.holdout_psnr - self.holdout_psnr_feed_forward

    @classmethod
    def from_json(cls, body: Mapping[str, Any]) -> FittedSummary:
        def number(name: str) -> Optional[float]:
            value = body.get(name)
            return None if value is None else float(value)

        try:
            width, height = body.get("resolution") or (0, 0)
            return cls(
                job_id=body.get("job_id", ""),
                preset=body.get("preset", ""),
                gaussians=int(body.get("gaussians", 0)),
                static_gaussians=int(body.get("static_gaussians", 0)),
                keyframes=tuple(float(t) for t in body.get("keyframes", ())),
                steps=int(body.get("steps", 0)),
                seconds=float(body.get("seconds", 0.0)),
                frames=int(body.get("frames", 0)),
                resolution=(int(width), int(height)),
                holdout_frames=tuple(int(k) for k in body.get("holdout_frames", ())),
                holdout_times=tuple(float(t) for t in body.get("holdout_times", ())),
                holdout_psnr=number("holdout_psnr"),
                holdout_psnr_feed_forward=number("holdout_psnr_feed_forward"),
                train_psnr=number("train_psnr"),
                stopped_early=bool(body.get("stopped_early", False)),
                created_at=int(body.get("created_at", 0)),
                notes=tuple(str(n) for n in body.get("notes", ())),
                raw=dict(body),
            )
        except (TypeError, ValueError) as e:
            raise FormatError(f"not a fitted scene's summary ({e!r})") from None


@dataclass(frozen=True)
class Clip:
    """An uploaded, encoded clip. ``span`` is the context span: decode and render take times
    in ``[span[0], span[1]]`` seconds. ``fitted`` summarises its fitted scene once a fit made
    one (``None`` before; the list of clips leaves it out, :meth:`Client.clip
    <c4g_client.Client.clip>` says)."""

    id: str
    model: str
    state: str
    context_times: Tuple[float, ...]
    span: Tuple[float, float]
    source: ClipSource
    feature_bytes: int
    created_at: int
    created: Optional[bool]
    raw: Dict[str, Any] = field(repr=False, compare=False)
    fitted: Optional[FittedSummary] = None

    @classmethod
    def from_json(cls, body: Mapping[str, Any], created: Optional[bool] = None) -> Clip:
        try:
            source = body["source"]
            fitted = body.get("fitted")
            return cls(
                id=body["id"],
                model=body.get("model", ""),
                state=body.get("state", ""),
                context_times=tuple(float(t) for t in body["context_times"]),
                span=(float(body["span"][0]), float(body["span"][1])),
                source=ClipSource(
                    kind=source.get("kind", ""),
                    frames=int(source.get("frames", 0)),
                    width=int(source.get("width", 0)),
                    height=int(source.get("height", 0)),
                    duration=float(source.get("duration", 0.0)),
                    fps=float(source.get("fps", 0.0)),
                    warnings=tuple(source.get("warnings", ())),
                ),
                feature_bytes=int(body.get("feature_bytes", 0)),
                created_at=int(body.get("created_at", 0)),
                created=body.get("created", created),
                raw=dict(body),
                fitted=FittedSummary.from_json(fitted) if isinstance(fitted, Mapping) else None,
            )
        except (KeyError, TypeError, ValueError, IndexError) as e:
            raise FormatError(f"not a clip record ({e!r})") from None


@dataclass(frozen=True)
class Model:
    """The served model package (``GET /v1/models``): its input size, Gaussians per set,
    renderer and the server's limits. ``feature_lifting`` is the width F of its feature decoder
    (the lifted features of ``decode(..., features=True)``, the feature renders and segments),
    ``None`` for a package without one."""

    name: str
    version: str
    input_width: int
    input_height: int
    gaussians_per_set: int
    renderer: str
    footprint: str
    limits: Dict[str, float]
    feature_lifting: Optional[int]
    raw: Dict[str, Any] = field(repr=False, compare=False)

    @classmethod
    def from_json(cls, body: Mapping[str, Any]) -> Model:
        size = body.get("input", {})
        return cls(
            name=body.get("name", ""),
            version=body.get("version", ""),
            input_width=int(size.get("width", 0)),
            input_height=int(size.get("height", 0)),
            gaussians_per_set=int(body.get("gaussians_per_set", 0)),
            renderer=body.get("renderer", ""),
            footprint=body.get("footprint", ""),
            limits=dict(body.get("limits", {})),
            feature_lifting=int(body["feature_lifting"]) if body.get("feature_lifting") else None,
            raw=dict(body),
        )


@dataclass(frozen=True)
class JobProgress:
    """Where a running job is: ``step`` of ``steps`` in ``stage`` (``denoising``, ...; a fit's
    ``preparing``, ``fitting``, ``storing``). A fit also reports its ``loss``, the mean PSNR of
    its held-out frames when it last scored them (``holdout_psnr``, dB), its ``gaussians`` per
    keyframe and the seconds its worker has spent (``elapsed_s``); ``None`` for a refinement."""

    step: int
    steps: int
    stage: str
    loss: Optional[float] = None
    holdout_psnr: Optional[float] = None
    gaussians: Optional[int] = None
    elapsed_s: Optional[float] = None

    @classmethod
    def from_json(cls, body: Mapping[str, Any]) -> JobProgress:
        def number(name: str) -> Optional[float]:
            value = body.get(name)
            return None if value is None else float(value)

        gaussians = body.get("gaussians")
        return cls(
            int(body.get("step", 0)),
            int(body.get("steps", 0)),
            body.get("stage", ""),
            loss=number("loss"),
            holdout_psnr=number("holdout_psnr"),
            gaussians=None if gaussians is None else int(gaussians),
            elapsed_s=number("elapsed_s"),
        )

    @property
    def fraction(self) -> float:
        return self.step / self.steps if self.steps else 0.0


@dataclass(frozen=True)
class Job:
    """A job's record (``GET /v1/jobs/{id}``, and every job event): ``kind`` is ``refine`` or
    ``fit``. A fit's result is the clip's fitted scene (:attr:`Clip.fitted`), not a video."""

    id: str
    clip_id: str
    state: str
    attempt: int
    max_attempts: int
    worker: Optional[str]
    progress: Optional[JobProgress]
    error: Optional[str]
    history: Tuple[str, ...]
    result_frames: int
    seconds: Optional[float]
    cancel_requested: bool
    raw: Dict[str, Any] = field(repr=False, compare=False)
    kind: str = ""

    @property
    def is_terminal(self) -> bool:
        """In a state the job never leaves: ``done``, ``failed`` or ``cancelled``."""
        return self.state in TERMINAL_STATES

    @property
    def is_done(self) -> bool:
        """The result is stored."""
        return self.state == "done"

    @classmethod
    def from_json(cls, body: Mapping[str, Any]) -> Job:
        try:
            progress = body.get("progress")
            return cls(
                id=body["id"],
                clip_id=body.get("clip_id", ""),
                state=body.get("state", ""),
                attempt=int(body.get("attempt", 0)),
                max_attempts=int(body.get("max_attempts", 0)),
                worker=body.get("worker"),
                progress=JobProgress.from_json(progress) if isinstance(progress, Mapping) else None,
                error=body.get("error"),
                history=tuple(body.get("history", ())),
                result_frames=int(body.get("result_frames", 0)),
                seconds=body.get("seconds"),
                cancel_requested=bool(body.get("cancel_requested", False)),
                raw=dict(body),
                kind=body.get("kind", ""),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            raise FormatError(f"not a job record ({e!r})") from None


@dataclass(frozen=True)
class Export:
    """A 4D file other viewers open (or a one-time ``.ply`` / ``.splat``): the bytes, the name
    the server suggests, how many sets it holds, for ``.splatv`` how far the fit strays from
    the sets (``fit_error``: ``{"max": ..., "rms": ...}``, scene units), and the scene the sets
    came from (``scene``: ``feed-forward`` or ``fitted``)."""

    data: bytes
    format: str
    filename: Optional[str]
    sets: Optional[int]
    fit_error: Optional[Dict[str, float]]
    scene: Optional[str] = None

    def save(self, path: PathLike) -> None:
        """Writes the file as the server sent it."""
        with open(path, "wb") as f:
            f.write(self.data)

    def __len__(self) -> int:
        return len(self.data)

    def __repr__(self) -> str:
        scene = "" if self.scene is None else f", {self.scene}"
        return f"Export({self.format}, {len(self.data)} bytes, {self.sets} sets{scene})"


@dataclass(frozen=True, eq=False)
class Mask:
    """Where a segment's Gaussians are at time ``t``: their own render's alpha at 0.5 or more
    (amodal: a selected Gaussian behind others still marks its pixels), ``area`` pixels set.
    ``counts`` is the server's run-length code, alternating runs over the pixels in row-major
    order starting with unset pixels; ``array`` is the ``(height, width)`` ``bool`` mask."""

    t: float
    area: int
    counts: Tuple[int, ...]
    width: int
    height: int

    @property
    def array(self) -> np.ndarray:
        runs = np.asarray(self.counts, dtype=np.int64)
        values = np.arange(runs.size) % 2 == 1
        return np.repeat(values, runs).reshape(self.height, self.width)

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        return self.array if dtype is None else self.array.astype(dtype)

    def __repr__(self) -> str:
        return f"Mask(t={self.t:g} s, {self.area} of {self.width}x{self.height} pixels)"


@dataclass(frozen=True, eq=False)
class Segment:
    """The answer of ``POST /v1/clips/{id}/segment``: the Gaussians (indices, the same Gaussians
    at every time) whose lifted feature at ``t`` has a cosine similarity of at least
    ``threshold`` with ``feature`` (the clicked pixel's, or the one given), and one
    :class:`Mask` of ``width`` × ``height`` per answered time, in order."""

    width: int
    height: int
    t: float
    threshold: float
    feature: np.ndarray
    gaussians: np.ndarray
    masks: Tuple[Mask, ...]
    raw: Dict[str, Any] = field(repr=False)

    @classmethod
    def from_json(cls, body: Mapping[str, Any]) -> Segment:
        try:
            width, height = int(body["width"]), int(body["height"])
            masks = []
            for m in body["masks"]:
                counts = tuple(int(c) for c in m["counts"])
                # Checked here, so a mask's array never allocates more than its image.
                if any(c < 0 for c in counts) or sum(counts) != width * height:
                    raise FormatError(f"a mask's runs sum to the {width}x{height} pixels; got {sum(counts)}")
                masks.append(Mask(float(m["t"]), int(m["area"]), counts, width, height))
            return cls(
                width=width,
                height=height,
                t=float(body["t"]),
                threshold=float(body["threshold"]),
                feature=np.asarray(body["feature"], dtype=np.float32),
                gaussians=np.asarray(body["gaussians"], dtype=np.int64).reshape(-1),
                masks=tuple(masks),
                raw=dict(body),
            )
        except (KeyError, TypeError, ValueError) as e:
            if isinstance(e, FormatError):
                raise
            raise FormatError(f"not a segment ({e!r})") from None

    def __repr__(self) -> str:
        return (
            f"Segment(t={self.t:g} s, {len(self.gaussians)} Gaussians, {len(self.masks)} masks "
            f"of {self.width}x{self.height})"
        )


def filename_from(disposition: Optional[str]) -> Optional[str]:
    """The ``filename`` of a ``Content-Disposition`` header."""
    if not disposition:
        return None
    match = re.search(r'filename="([^"]*)"', disposition) or re.search(r"filename=([^;\s]+)", disposition)
    return match.group(1) if match else None


def fit_error_from(header: Optional[str]) -> Optional[Dict[str, float]]:
    """``X-C4G-Fit-Position-Error: max=..., rms=...`` as a dict."""
    if not header:
        return None
    out: Dict[str, float] = {}
    for part in header.split(","):
        name, _, value = part.strip().partition("=")
        try:
            out[name] = float(value)
        except ValueError:
            continue
    return out


def jobs_from(body: Mapping[str, Any]) -> List[Job]:
    return [Job.from_json(j) for j in body.get("jobs", [])]
