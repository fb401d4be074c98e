from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class MediaKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    MEDIA_KIND_UNSPECIFIED: _ClassVar[MediaKind]
    MEDIA_KIND_VIDEO: _ClassVar[MediaKind]
    MEDIA_KIND_ZIP: _ClassVar[MediaKind]
    MEDIA_KIND_TAR: _ClassVar[MediaKind]

class ClipState(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    CLIP_STATE_UNSPECIFIED: _ClassVar[ClipState]
    CLIP_STATE_ENCODING: _ClassVar[ClipState]
    CLIP_STATE_READY: _ClassVar[ClipState]

class Precision(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    PRECISION_UNSPECIFIED: _ClassVar[Precision]
    PRECISION_F32: _ClassVar[Precision]
    PRECISION_F16: _ClassVar[Precision]

class Quality(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    QUALITY_UNSPECIFIED: _ClassVar[Quality]
    QUALITY_EXACT: _ClassVar[Quality]
    QUALITY_BALANCED: _ClassVar[Quality]
    QUALITY_FAST: _ClassVar[Quality]

class ImageFormat(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IMAGE_FORMAT_UNSPECIFIED: _ClassVar[ImageFormat]
    IMAGE_FORMAT_PNG: _ClassVar[ImageFormat]
    IMAGE_FORMAT_DEPTH_F32: _ClassVar[ImageFormat]
    IMAGE_FORMAT_ALPHA_F32: _ClassVar[ImageFormat]
    IMAGE_FORMAT_FEATURES_F32: _ClassVar[ImageFormat]
    IMAGE_FORMAT_FEATURES_PCA_PNG: _ClassVar[ImageFormat]

class Tracker(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    TRACKER_UNSPECIFIED: _ClassVar[Tracker]
    TRACKER_GAUSSIANS: _ClassVar[Tracker]
    TRACKER_FEATURES: _ClassVar[Tracker]
MEDIA_KIND_UNSPECIFIED: MediaKind
MEDIA_KIND_VIDEO: MediaKind
MEDIA_KIND_ZIP: MediaKind
MEDIA_KIND_TAR: MediaKind
CLIP_STATE_UNSPECIFIED: ClipState
CLIP_STATE_ENCODING: ClipState
CLIP_STATE_READY: ClipState
PRECISION_UNSPECIFIED: Precision
PRECISION_F32: Precision
PRECISION_F16: Precision
QUALITY_UNSPECIFIED: Quality
QUALITY_EXACT: Quality
QUALITY_BALANCED: Quality
QUALITY_FAST: Quality
IMAGE_FORMAT_UNSPECIFIED: ImageFormat
IMAGE_FORMAT_PNG: ImageFormat
IMAGE_FORMAT_DEPTH_F32: ImageFormat
IMAGE_FORMAT_ALPHA_F32: ImageFormat
IMAGE_FORMAT_FEATURES_F32: ImageFormat
IMAGE_FORMAT_FEATURES_PCA_PNG: ImageFormat
TRACKER_UNSPECIFIED: Tracker
TRACKER_GAUSSIANS: Tracker
TRACKER_FEATURES: Tracker

class UploadRequest(_message.Message):
    __slots__ = ("header", "chunk")
    HEADER_FIELD_NUMBER: _ClassVar[int]
    CHUNK_FIELD_NUMBER: _ClassVar[int]
    header: UploadHeader
    chunk: bytes
    def __init__(self, header: _Optional[_Union[UploadHeader, _Mapping]] = ..., chunk: _Optional[bytes] = ...) -> None: ...

class UploadHeader(_message.Message):
    __slots__ = ("kind", "filename", "fps", "timestamps", "sampling", "cameras")
    KIND_FIELD_NUMBER: _ClassVar[int]
    FILENAME_FIELD_NUMBER: _ClassVar[int]
    FPS_FIELD_NUMBER: _ClassVar[int]
    TIMESTAMPS_FIELD_NUMBER: _ClassVar[int]
    SAMPLING_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    kind: MediaKind
    filename: str
    fps: float
    timestamps: _containers.RepeatedScalarFieldContainer[float]
    sampling: ClipSampling
    cameras: GivenCameras
    def __init__(self, kind: _Optional[_Union[MediaKind, str]] = ..., filename: _Optional[str] = ..., fps: _Optional[float] = ..., timestamps: _Optional[_Iterable[float]] = ..., sampling: _Optional[_Union[ClipSampling, _Mapping]] = ..., cameras: _Optional[_Union[GivenCameras, _Mapping]] = ...) -> None: ...

class GivenCameras(_message.Message):
    __slots__ = ("json", "colmap", "transforms", "names")
    JSON_FIELD_NUMBER: _ClassVar[int]
    COLMAP_FIELD_NUMBER: _ClassVar[int]
    TRANSFORMS_FIELD_NUMBER: _ClassVar[int]
    NAMES_FIELD_NUMBER: _ClassVar[int]
    json: str
    colmap: ColmapText
    transforms: str
    names: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, json: _Optional[str] = ..., colmap: _Optional[_Union[ColmapText, _Mapping]] = ..., transforms: _Optional[str] = ..., names: _Optional[_Iterable[str]] = ...) -> None: ...

class ColmapText(_message.Message):
    __slots__ = ("cameras_txt", "images_txt")
    CAMERAS_TXT_FIELD_NUMBER: _ClassVar[int]
    IMAGES_TXT_FIELD_NUMBER: _ClassVar[int]
    cameras_txt: str
    images_txt: str
    def __init__(self, cameras_txt: _Optional[str] = ..., images_txt: _Optional[str] = ...) -> None: ...

class ClipSampling(_message.Message):
    __slots__ = ("max_frames", "stride", "start", "end")
    MAX_FRAMES_FIELD_NUMBER: _ClassVar[int]
    STRIDE_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    END_FIELD_NUMBER: _ClassVar[int]
    max_frames: int
    stride: int
    start: float
    end: float
    def __init__(self, max_frames: _Optional[int] = ..., stride: _Optional[int] = ..., start: _Optional[float] = ..., end: _Optional[float] = ...) -> None: ...

class ClipRef(_message.Message):
    __slots__ = ("clip_id",)
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    def __init__(self, clip_id: _Optional[str] = ...) -> None: ...

class Clip(_message.Message):
    __slots__ = ("clip_id", "model", "context_times", "source_frames", "source_width", "source_height", "duration", "state", "feature_bytes", "source_kind", "source_fps", "created", "source_warnings", "cameras", "fitted_json")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    MODEL_FIELD_NUMBER: _ClassVar[int]
    CONTEXT_TIMES_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FRAMES_FIELD_NUMBER: _ClassVar[int]
    SOURCE_WIDTH_FIELD_NUMBER: _ClassVar[int]
    SOURCE_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DURATION_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    FEATURE_BYTES_FIELD_NUMBER: _ClassVar[int]
    SOURCE_KIND_FIELD_NUMBER: _ClassVar[int]
    SOURCE_FPS_FIELD_NUMBER: _ClassVar[int]
    CREATED_FIELD_NUMBER: _ClassVar[int]
    SOURCE_WARNINGS_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    FITTED_JSON_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    model: str
    context_times: _containers.RepeatedScalarFieldContainer[float]
    source_frames: int
    source_width: int
    source_height: int
    duration: float
    state: ClipState
    feature_bytes: int
    source_kind: str
    source_fps: float
    created: bool
    source_warnings: _containers.RepeatedScalarFieldContainer[str]
    cameras: ClipCameras
    fitted_json: str
    def __init__(self, clip_id: _Optional[str] = ..., model: _Optional[str] = ..., context_times: _Optional[_Iterable[float]] = ..., source_frames: _Optional[int] = ..., source_width: _Optional[int] = ..., source_height: _Optional[int] = ..., duration: _Optional[float] = ..., state: _Optional[_Union[ClipState, str]] = ..., feature_bytes: _Optional[int] = ..., source_kind: _Optional[str] = ..., source_fps: _Optional[float] = ..., created: _Optional[bool] = ..., source_warnings: _Optional[_Iterable[str]] = ..., cameras: _Optional[_Union[ClipCameras, _Mapping]] = ..., fitted_json: _Optional[str] = ...) -> None: ...

class ClipCameras(_message.Message):
    __slots__ = ("format", "scale", "frames", "notes")
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    SCALE_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    NOTES_FIELD_NUMBER: _ClassVar[int]
    format: str
    scale: float
    frames: _containers.RepeatedCompositeFieldContainer[ContextCamera]
    notes: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, format: _Optional[str] = ..., scale: _Optional[float] = ..., frames: _Optional[_Iterable[_Union[ContextCamera, _Mapping]]] = ..., notes: _Optional[_Iterable[str]] = ...) -> None: ...

class ContextCamera(_message.Message):
    __slots__ = ("time", "world_to_camera", "fx", "fy", "cx", "cy")
    TIME_FIELD_NUMBER: _ClassVar[int]
    WORLD_TO_CAMERA_FIELD_NUMBER: _ClassVar[int]
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    time: float
    world_to_camera: _containers.RepeatedScalarFieldContainer[float]
    fx: float
    fy: float
    cx: float
    cy: float
    def __init__(self, time: _Optional[float] = ..., world_to_camera: _Optional[_Iterable[float]] = ..., fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ...) -> None: ...

class ListClipsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListClipsResponse(_message.Message):
    __slots__ = ("clips",)
    CLIPS_FIELD_NUMBER: _ClassVar[int]
    clips: _containers.RepeatedCompositeFieldContainer[Clip]
    def __init__(self, clips: _Optional[_Iterable[_Union[Clip, _Mapping]]] = ...) -> None: ...

class DeleteClipResponse(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class GaussianSet(_message.Message):
    __slots__ = ("count", "precision", "means", "scales", "rotations", "opacities", "colors", "feature_width", "features")
    COUNT_FIELD_NUMBER: _ClassVar[int]
    PRECISION_FIELD_NUMBER: _ClassVar[int]
    MEANS_FIELD_NUMBER: _ClassVar[int]
    SCALES_FIELD_NUMBER: _ClassVar[int]
    ROTATIONS_FIELD_NUMBER: _ClassVar[int]
    OPACITIES_FIELD_NUMBER: _ClassVar[int]
    COLORS_FIELD_NUMBER: _ClassVar[int]
    FEATURE_WIDTH_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    count: int
    precision: Precision
    means: bytes
    scales: bytes
    rotations: bytes
    opacities: bytes
    colors: bytes
    feature_width: int
    features: bytes
    def __init__(self, count: _Optional[int] = ..., precision: _Optional[_Union[Precision, str]] = ..., means: _Optional[bytes] = ..., scales: _Optional[bytes] = ..., rotations: _Optional[bytes] = ..., opacities: _Optional[bytes] = ..., colors: _Optional[bytes] = ..., feature_width: _Optional[int] = ..., features: _Optional[bytes] = ...) -> None: ...

class DecodeRequest(_message.Message):
    __slots__ = ("clip_id", "times", "precision", "keyframes", "quality", "prune", "scene", "features")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    TIMES_FIELD_NUMBER: _ClassVar[int]
    PRECISION_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    PRUNE_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    FEATURES_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    times: _containers.RepeatedScalarFieldContainer[float]
    precision: Precision
    keyframes: Keyframes
    quality: Quality
    prune: Prune
    scene: str
    features: bool
    def __init__(self, clip_id: _Optional[str] = ..., times: _Optional[_Iterable[float]] = ..., precision: _Optional[_Union[Precision, str]] = ..., keyframes: _Optional[_Union[Keyframes, _Mapping]] = ..., quality: _Optional[_Union[Quality, str]] = ..., prune: _Optional[_Union[Prune, _Mapping]] = ..., scene: _Optional[str] = ..., features: _Optional[bool] = ...) -> None: ...

class Prune(_message.Message):
    __slots__ = ("contribution_px", "opacity", "drop_queries")
    CONTRIBUTION_PX_FIELD_NUMBER: _ClassVar[int]
    OPACITY_FIELD_NUMBER: _ClassVar[int]
    DROP_QUERIES_FIELD_NUMBER: _ClassVar[int]
    contribution_px: float
    opacity: float
    drop_queries: bool
    def __init__(self, contribution_px: _Optional[float] = ..., opacity: _Optional[float] = ..., drop_queries: _Optional[bool] = ...) -> None: ...

class Keyframes(_message.Message):
    __slots__ = ("every_s", "count", "adaptive")
    EVERY_S_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    ADAPTIVE_FIELD_NUMBER: _ClassVar[int]
    every_s: float
    count: int
    adaptive: AdaptiveKeyframes
    def __init__(self, every_s: _Optional[float] = ..., count: _Optional[int] = ..., adaptive: _Optional[_Union[AdaptiveKeyframes, _Mapping]] = ...) -> None: ...

class AdaptiveKeyframes(_message.Message):
    __slots__ = ("tolerance", "color_tolerance", "max", "min_interval_s")
    TOLERANCE_FIELD_NUMBER: _ClassVar[int]
    COLOR_TOLERANCE_FIELD_NUMBER: _ClassVar[int]
    MAX_FIELD_NUMBER: _ClassVar[int]
    MIN_INTERVAL_S_FIELD_NUMBER: _ClassVar[int]
    tolerance: float
    color_tolerance: float
    max: int
    min_interval_s: float
    def __init__(self, tolerance: _Optional[float] = ..., color_tolerance: _Optional[float] = ..., max: _Optional[int] = ..., min_interval_s: _Optional[float] = ...) -> None: ...

class DecodeResponse(_message.Message):
    __slots__ = ("frames", "scene")
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    frames: _containers.RepeatedCompositeFieldContainer[GaussianFrame]
    scene: str
    def __init__(self, frames: _Optional[_Iterable[_Union[GaussianFrame, _Mapping]]] = ..., scene: _Optional[str] = ...) -> None: ...

class GaussianFrame(_message.Message):
    __slots__ = ("time", "gaussians", "c4gv", "scene")
    TIME_FIELD_NUMBER: _ClassVar[int]
    GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    C4GV_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    time: float
    gaussians: GaussianSet
    c4gv: bytes
    scene: str
    def __init__(self, time: _Optional[float] = ..., gaussians: _Optional[_Union[GaussianSet, _Mapping]] = ..., c4gv: _Optional[bytes] = ..., scene: _Optional[str] = ...) -> None: ...

class CompactStream(_message.Message):
    __slots__ = ("position_error", "keyframe_interval")
    POSITION_ERROR_FIELD_NUMBER: _ClassVar[int]
    KEYFRAME_INTERVAL_FIELD_NUMBER: _ClassVar[int]
    position_error: float
    keyframe_interval: int
    def __init__(self, position_error: _Optional[float] = ..., keyframe_interval: _Optional[int] = ...) -> None: ...

class StreamGaussiansRequest(_message.Message):
    __slots__ = ("clip_id", "start", "end", "step", "fps", "precision", "keyframes", "quality", "prune", "compact", "scene")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    END_FIELD_NUMBER: _ClassVar[int]
    STEP_FIELD_NUMBER: _ClassVar[int]
    FPS_FIELD_NUMBER: _ClassVar[int]
    PRECISION_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    PRUNE_FIELD_NUMBER: _ClassVar[int]
    COMPACT_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    start: float
    end: float
    step: float
    fps: float
    precision: Precision
    keyframes: Keyframes
    quality: Quality
    prune: Prune
    compact: CompactStream
    scene: str
    def __init__(self, clip_id: _Optional[str] = ..., start: _Optional[float] = ..., end: _Optional[float] = ..., step: _Optional[float] = ..., fps: _Optional[float] = ..., precision: _Optional[_Union[Precision, str]] = ..., keyframes: _Optional[_Union[Keyframes, _Mapping]] = ..., quality: _Optional[_Union[Quality, str]] = ..., prune: _Optional[_Union[Prune, _Mapping]] = ..., compact: _Optional[_Union[CompactStream, _Mapping]] = ..., scene: _Optional[str] = ...) -> None: ...

class Intrinsics(_message.Message):
    __slots__ = ("fx", "fy", "cx", "cy")
    FX_FIELD_NUMBER: _ClassVar[int]
    FY_FIELD_NUMBER: _ClassVar[int]
    CX_FIELD_NUMBER: _ClassVar[int]
    CY_FIELD_NUMBER: _ClassVar[int]
    fx: float
    fy: float
    cx: float
    cy: float
    def __init__(self, fx: _Optional[float] = ..., fy: _Optional[float] = ..., cx: _Optional[float] = ..., cy: _Optional[float] = ...) -> None: ...

class Camera(_message.Message):
    __slots__ = ("world_to_camera", "intrinsics", "input")
    WORLD_TO_CAMERA_FIELD_NUMBER: _ClassVar[int]
    INTRINSICS_FIELD_NUMBER: _ClassVar[int]
    INPUT_FIELD_NUMBER: _ClassVar[int]
    world_to_camera: _containers.RepeatedScalarFieldContainer[float]
    intrinsics: Intrinsics
    input: InputCamera
    def __init__(self, world_to_camera: _Optional[_Iterable[float]] = ..., intrinsics: _Optional[_Union[Intrinsics, _Mapping]] = ..., input: _Optional[_Union[InputCamera, _Mapping]] = ...) -> None: ...

class InputCamera(_message.Message):
    __slots__ = ("at", "start", "end")
    AT_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    END_FIELD_NUMBER: _ClassVar[int]
    at: float
    start: float
    end: float
    def __init__(self, at: _Optional[float] = ..., start: _Optional[float] = ..., end: _Optional[float] = ...) -> None: ...

class RenderRequest(_message.Message):
    __slots__ = ("clip_id", "time", "camera", "width", "height", "format", "background", "quality", "prune", "scene")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    BACKGROUND_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    PRUNE_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    time: float
    camera: Camera
    width: int
    height: int
    format: ImageFormat
    background: _containers.RepeatedScalarFieldContainer[float]
    quality: Quality
    prune: Prune
    scene: str
    def __init__(self, clip_id: _Optional[str] = ..., time: _Optional[float] = ..., camera: _Optional[_Union[Camera, _Mapping]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., format: _Optional[_Union[ImageFormat, str]] = ..., background: _Optional[_Iterable[float]] = ..., quality: _Optional[_Union[Quality, str]] = ..., prune: _Optional[_Union[Prune, _Mapping]] = ..., scene: _Optional[str] = ...) -> None: ...

class RenderTrajectoryRequest(_message.Message):
    __slots__ = ("clip_id", "start", "end", "frames", "preset_json", "cameras", "width", "height", "format", "camera", "background", "keyframes", "quality", "prune", "scene")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    START_FIELD_NUMBER: _ClassVar[int]
    END_FIELD_NUMBER: _ClassVar[int]
    FRAMES_FIELD_NUMBER: _ClassVar[int]
    PRESET_JSON_FIELD_NUMBER: _ClassVar[int]
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    BACKGROUND_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    PRUNE_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    start: float
    end: float
    frames: int
    preset_json: str
    cameras: _containers.RepeatedCompositeFieldContainer[Camera]
    width: int
    height: int
    format: ImageFormat
    camera: Camera
    background: _containers.RepeatedScalarFieldContainer[float]
    keyframes: Keyframes
    quality: Quality
    prune: Prune
    scene: str
    def __init__(self, clip_id: _Optional[str] = ..., start: _Optional[float] = ..., end: _Optional[float] = ..., frames: _Optional[int] = ..., preset_json: _Optional[str] = ..., cameras: _Optional[_Iterable[_Union[Camera, _Mapping]]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., format: _Optional[_Union[ImageFormat, str]] = ..., camera: _Optional[_Union[Camera, _Mapping]] = ..., background: _Optional[_Iterable[float]] = ..., keyframes: _Optional[_Union[Keyframes, _Mapping]] = ..., quality: _Optional[_Union[Quality, str]] = ..., prune: _Optional[_Union[Prune, _Mapping]] = ..., scene: _Optional[str] = ...) -> None: ...

class RenderedImage(_message.Message):
    __slots__ = ("time", "width", "height", "format", "data", "channels", "scene")
    TIME_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    FORMAT_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    CHANNELS_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    time: float
    width: int
    height: int
    format: ImageFormat
    data: bytes
    channels: int
    scene: str
    def __init__(self, time: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., format: _Optional[_Union[ImageFormat, str]] = ..., data: _Optional[bytes] = ..., channels: _Optional[int] = ..., scene: _Optional[str] = ...) -> None: ...

class TracksRequest(_message.Message):
    __slots__ = ("clip_id", "queries", "times", "width", "height", "quality", "keyframes", "prune", "tracker", "scene")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    QUERIES_FIELD_NUMBER: _ClassVar[int]
    TIMES_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    QUALITY_FIELD_NUMBER: _ClassVar[int]
    KEYFRAMES_FIELD_NUMBER: _ClassVar[int]
    PRUNE_FIELD_NUMBER: _ClassVar[int]
    TRACKER_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    queries: _containers.RepeatedCompositeFieldContainer[TrackQuery]
    times: _containers.RepeatedScalarFieldContainer[float]
    width: int
    height: int
    quality: Quality
    keyframes: Keyframes
    prune: Prune
    tracker: Tracker
    scene: str
    def __init__(self, clip_id: _Optional[str] = ..., queries: _Optional[_Iterable[_Union[TrackQuery, _Mapping]]] = ..., times: _Optional[_Iterable[float]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., quality: _Optional[_Union[Quality, str]] = ..., keyframes: _Optional[_Union[Keyframes, _Mapping]] = ..., prune: _Optional[_Union[Prune, _Mapping]] = ..., tracker: _Optional[_Union[Tracker, str]] = ..., scene: _Optional[str] = ...) -> None: ...

class TrackQuery(_message.Message):
    __slots__ = ("time", "x", "y")
    TIME_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    time: float
    x: float
    y: float
    def __init__(self, time: _Optional[float] = ..., x: _Optional[float] = ..., y: _Optional[float] = ...) -> None: ...

class TracksResponse(_message.Message):
    __slots__ = ("width", "height", "times", "tracks", "tracker", "scene")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    TIMES_FIELD_NUMBER: _ClassVar[int]
    TRACKS_FIELD_NUMBER: _ClassVar[int]
    TRACKER_FIELD_NUMBER: _ClassVar[int]
    SCENE_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    times: _containers.RepeatedScalarFieldContainer[float]
    tracks: _containers.RepeatedCompositeFieldContainer[Track]
    tracker: Tracker
    scene: str
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., times: _Optional[_Iterable[float]] = ..., tracks: _Optional[_Iterable[_Union[Track, _Mapping]]] = ..., tracker: _Optional[_Union[Tracker, str]] = ..., scene: _Optional[str] = ...) -> None: ...

class Track(_message.Message):
    __slots__ = ("query", "anchored", "points")
    QUERY_FIELD_NUMBER: _ClassVar[int]
    ANCHORED_FIELD_NUMBER: _ClassVar[int]
    POINTS_FIELD_NUMBER: _ClassVar[int]
    query: TrackQuery
    anchored: bool
    points: _containers.RepeatedCompositeFieldContainer[TrackPoint]
    def __init__(self, query: _Optional[_Union[TrackQuery, _Mapping]] = ..., anchored: _Optional[bool] = ..., points: _Optional[_Iterable[_Union[TrackPoint, _Mapping]]] = ...) -> None: ...

class TrackPoint(_message.Message):
    __slots__ = ("time", "x", "y", "visible", "depth", "position", "similarity")
    TIME_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    VISIBLE_FIELD_NUMBER: _ClassVar[int]
    DEPTH_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    SIMILARITY_FIELD_NUMBER: _ClassVar[int]
    time: float
    x: float
    y: float
    visible: bool
    depth: float
    position: _containers.RepeatedScalarFieldContainer[float]
    similarity: float
    def __init__(self, time: _Optional[float] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., visible: _Optional[bool] = ..., depth: _Optional[float] = ..., position: _Optional[_Iterable[float]] = ..., similarity: _Optional[float] = ...) -> None: ...

class SegmentRequest(_message.Message):
    __slots__ = ("clip_id", "click", "feature", "threshold", "times", "camera", "width", "height")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    CLICK_FIELD_NUMBER: _ClassVar[int]
    FEATURE_FIELD_NUMBER: _ClassVar[int]
    THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    TIMES_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    click: SegmentClick
    feature: FeatureSelection
    threshold: float
    times: _containers.RepeatedScalarFieldContainer[float]
    camera: Camera
    width: int
    height: int
    def __init__(self, clip_id: _Optional[str] = ..., click: _Optional[_Union[SegmentClick, _Mapping]] = ..., feature: _Optional[_Union[FeatureSelection, _Mapping]] = ..., threshold: _Optional[float] = ..., times: _Optional[_Iterable[float]] = ..., camera: _Optional[_Union[Camera, _Mapping]] = ..., width: _Optional[int] = ..., height: _Optional[int] = ...) -> None: ...

class SegmentClick(_message.Message):
    __slots__ = ("time", "x", "y")
    TIME_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    time: float
    x: float
    y: float
    def __init__(self, time: _Optional[float] = ..., x: _Optional[float] = ..., y: _Optional[float] = ...) -> None: ...

class FeatureSelection(_message.Message):
    __slots__ = ("feature", "time")
    FEATURE_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    feature: _containers.RepeatedScalarFieldContainer[float]
    time: float
    def __init__(self, feature: _Optional[_Iterable[float]] = ..., time: _Optional[float] = ...) -> None: ...

class SegmentResponse(_message.Message):
    __slots__ = ("width", "height", "time", "threshold", "feature", "gaussians", "masks")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    FEATURE_FIELD_NUMBER: _ClassVar[int]
    GAUSSIANS_FIELD_NUMBER: _ClassVar[int]
    MASKS_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    time: float
    threshold: float
    feature: _containers.RepeatedScalarFieldContainer[float]
    gaussians: _containers.RepeatedScalarFieldContainer[int]
    masks: _containers.RepeatedCompositeFieldContainer[Mask]
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., time: _Optional[float] = ..., threshold: _Optional[float] = ..., feature: _Optional[_Iterable[float]] = ..., gaussians: _Optional[_Iterable[int]] = ..., masks: _Optional[_Iterable[_Union[Mask, _Mapping]]] = ...) -> None: ...

class Mask(_message.Message):
    __slots__ = ("time", "area", "counts")
    TIME_FIELD_NUMBER: _ClassVar[int]
    AREA_FIELD_NUMBER: _ClassVar[int]
    COUNTS_FIELD_NUMBER: _ClassVar[int]
    time: float
    area: int
    counts: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, time: _Optional[float] = ..., area: _Optional[int] = ..., counts: _Optional[_Iterable[int]] = ...) -> None: ...

class RecoverCamerasRequest(_message.Message):
    __slots__ = ("clip_id", "refine_focal")
    CLIP_ID_FIELD_NUMBER: _ClassVar[int]
    REFINE_FOCAL_FIELD_NUMBER: _ClassVar[int]
    clip_id: str
    refine_focal: bool
    def __init__(self, clip_id: _Optional[str] = ..., refine_focal: _Optional[bool] = ...) -> None: ...

class RecoveredCameras(_message.Message):
    __slots__ = ("cameras", "fits")
    CAMERAS_FIELD_NUMBER: _ClassVar[int]
    FITS_FIELD_NUMBER: _ClassVar[int]
    cameras: ClipCameras
    fits: _containers.RepeatedCompositeFieldContainer[FrameFit]
    def __init__(self, cameras: _Optional[_Union[ClipCameras, _Mapping]] = ..., fits: _Optional[_Iterable[_Union[FrameFit, _Mapping]]] = ...) -> None: ...

class FrameFit(_message.Message):
    __slots__ = ("time", "initial_residual", "residual", "confidence", "coverage", "conditioning", "iterations", "converged")
    TIME_FIELD_NUMBER: _ClassVar[int]
    INITIAL_RESIDUAL_FIELD_NUMBER: _ClassVar[int]
    RESIDUAL_FIELD_NUMBER: _ClassVar[int]
    CONFIDENCE_FIELD_NUMBER: _ClassVar[int]
    COVERAGE_FIELD_NUMBER: _ClassVar[int]
    CONDITIONING_FIELD_NUMBER: _ClassVar[int]
    ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    CONVERGED_FIELD_NUMBER: _ClassVar[int]
    time: float
    initial_residual: float
    residual: float
    confidence: float
    coverage: float
    conditioning: float
    iterations: int
    converged: bool
    def __init__(self, time: _Optional[float] = ..., initial_residual: _Optional[float] = ..., residual: _Optional[float] = ..., confidence: _Optional[float] = ..., coverage: _Optional[float] = ..., conditioning: _Optional[float] = ..., iterations: _Optional[int] = ..., converged: _Optional[bool] = ...) -> None: ...

class ListModelsRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class ListModelsResponse(_message.Message):
    __slots__ = ("models",)
    MODELS_FIELD_NUMBER: _ClassVar[int]
    models: _containers.RepeatedCompositeFieldContainer[Model]
    def __init__(self, models: _Optional[_Iterable[_Union[Model, _Mapping]]] = ...) -> None: ...

class Model(_message.Message):
    __slots__ = ("name", "version", "input_width", "input_height", "gaussians_per_set", "manifest_json")
    NAME_FIELD_NUMBER: _ClassVar[int]
    VERSION_FIELD_NUMBER: _ClassVar[int]
    INPUT_WIDTH_FIELD_NUMBER: _ClassVar[int]
    INPUT_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    GAUSSIANS_PER_SET_FIELD_NUMBER: _ClassVar[int]
    MANIFEST_JSON_FIELD_NUMBER: _ClassVar[int]
    name: str
    version: str
    input_width: int
    input_height: int
    gaussians_per_set: int
    manifest_json: str
    def __init__(self, name: _Optional[str] = ..., version: _Optional[str] = ..., input_width: _Optional[int] = ..., input_height: _Optional[int] = ..., gaussians_per_set: _Optional[int] = ..., manifest_json: _Optional[str] = ...) -> None: ...
