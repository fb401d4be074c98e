"""c4g-client: the Python client of the c4g service (C4G, feed-forward 4D Gaussian
reconstruction), with NumPy arrays out, PyTorch and gsplat on request.

>>> from c4g_client import Client
>>> with Client("http://127.0.0.1:8080") as c4g:
...     clip = c4g.upload("clip.mp4")
...     gaussians = c4g.decode(clip.id, t=0.5)      # means, quats, scales, opacities, colors
...     c4g.render(clip.id, t=0.5)                  # an Image; shows itself in a notebook

Table of contents (each module is one idea; the names below are the public surface):

==================== ==========================================================================
module               what
==================== ==========================================================================
``_client``          :class:`Client`: every REST operation, blocking; gRPC streaming and decodes
``_async_client``    :class:`AsyncClient`: the same, for asyncio
``_endpoints``       the REST contract: each operation's request and how its answer is read
``_http``            base URL, API key, the request type both clients send, error answers
``_errors``          :class:`C4GError` and one class per server error ``kind``
``_sets``            :class:`GaussianSet`: NumPy arrays in gsplat's conventions (and the lifted
                     ``features``, when asked for); ``to_torch()``, ``to_ply()``, ``to_splat()``
``_ply``             a set as the 3DGS ``.ply``; :data:`SCALE_FLOOR`, the floor under a scale
                     before its logarithm
``_splat``           a set as antimatter15's ``.splat``
``_libm``            the C library's ``exp`` and ``log`` over arrays, bit for bit, at NumPy's speed
``_c4gs``            the ``C4GS`` binary sets (f32/f16, versions 1 and 2) the decodes are fetched as
``_c4gv``            :class:`C4GVDecoder`: the compact 4D stream, decoded incrementally
``_stream``          chunked answers as iterators: the C4GV stream, a job's events
``_sse``             server-sent events, chunk by chunk
``_grpc``            ``StreamGaussians`` and ``Decode`` over gRPC (extra ``grpc``); ``_proto`` its
                     messages
``_upload``          upload bodies: files, folders, bytes, NumPy frames, with progress
``_records``         :class:`Clip` (its :class:`FittedSummary`), :class:`Model`, :class:`Job`,
                     :class:`Export`, :class:`Segment` (a :class:`Mask` a time)
``_camera``          :class:`Camera`, :class:`Intrinsics`, presets :class:`Orbit` ...
``_approx``          :data:`Quality`, :class:`Keyframes`, :class:`Prune`, :data:`Scene`
``_media``           :class:`Image`, :class:`ScalarImage`, :class:`FeatureImage`, :class:`Video`,
                     notebook display
``_png``             PNG in and out with NumPy alone
``_gsplat``          :func:`render_with_gsplat`: the same set through gsplat, when installed
==================== ==========================================================================
"""

from ._approx import Keyframes, Prune, Quality, Scene
from ._async_client import AsyncClient
from ._c4gs import decode as decode_c4gs
from ._c4gv import C4GVDecoder, IndexEntry
from ._c4gv import Header as C4GVHeader
from ._c4gv import decode as decode_c4gv
from ._camera import Camera, Dolly, Intrinsics, Orbit, Spiral
from ._client import Client
from ._errors import (
    ApiError,
    Busy,
    C4GError,
    Draining,
    FormatError,
    InsufficientStorage,
    InternalError,
    InvalidInput,
    NotFound,
    NotReady,
    Overloaded,
    RetryableError,
    StreamInterrupted,
    TimedOut,
    TooLarge,
    TransportError,
    Unauthorized,
    Unavailable,
    UnreadableMedia,
    Unsupported,
    UnsupportedMedia,
)
from ._gsplat import GsplatRender, GsplatUnavailable, gsplat_available, render_with_gsplat
from ._media import FeatureImage, Image, ScalarImage, Video
from ._ply import SCALE_FLOOR
from ._records import Clip, ClipSource, Export, FittedSummary, Job, JobProgress, Mask, Model, Segment
from ._sets import GaussianSet, TorchGaussianSet, stack
from ._stream import AsyncSetStream, SetStream

__version__ = "0.1.0"

__all__ = [
    "ApiError",
    "AsyncClient",
    "AsyncSetStream",
    "Busy",
    "C4GError",
    "C4GVDecoder",
    "C4GVHeader",
    "Camera",
    "Client",
    "Clip",
    "ClipSource",
    "Dolly",
    "Draining",
    "Export",
    "FeatureImage",
    "FittedSummary",
    "FormatError",
    "GaussianSet",
    "GsplatRender",
    "GsplatUnavailable",
    "Image",
    "IndexEntry",
    "InsufficientStorage",
    "InternalError",
    "Intrinsics",
    "InvalidInput",
    "Job",
    "JobProgress",
    "Keyframes",
    "Mask",
    "Model",
    "NotFound",
    "NotReady",
    "Orbit",
    "Overloaded",
    "Prune",
    "Quality",
    "RetryableError",
    "SCALE_FLOOR",
    "ScalarImage",
    "Scene",
    "Segment",
    "SetStream",
    "Spiral",
    "StreamInterrupted",
    "TimedOut",
    "TooLarge",
    "TorchGaussianSet",
    "TransportError",
    "Unauthorized",
    "Unavailable",
    "UnreadableMedia",
    "Unsupported",
    "UnsupportedMedia",
    "Video",
    "decode_c4gs",
    "decode_c4gv",
    "gsplat_available",
    "render_with_gsplat",
    "stack",
]
