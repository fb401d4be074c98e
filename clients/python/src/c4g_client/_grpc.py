"""gRPC ``StreamGaussians`` and ``Decode`` (``c4g.v1.C4G``, same port as REST): Gaussian sets
over a time range as an iterator, with the transport's flow control (the server decodes a
bounded number of sets ahead of a slow reader), and the sets at given times in one answer (the
one gRPC call that carries lifted features: ``DecodeRequest.features``). Needs the ``grpc``
extra (grpcio, protobuf).

The messages come from the committed ``_proto/c4g_pb2.py``; the calls are made with grpcio's
generic ``unary_stream`` / ``unary_unary`` on the method's path rather than a generated service
stub, so the package carries no grpcio-version-pinned code. Each set is packed columns (``f32``
or ``f16``, read like ``C4GS``, ``feature_width`` and ``features`` its sixth), or, for a compact
stream, a piece of one ``C4GV`` stream fed to the same incremental decoder as the REST stream.

A client opens one channel (one HTTP/2 connection) on its first gRPC call and makes every
later call on it, as its ``httpx`` pool does for REST: no connection set-up per call, and one
socket however many calls are made. The client closes it.

Errors carry the server's kind from the ``c4g-error-kind`` metadata entry, so a gRPC
``NOT_FOUND`` raises the same :class:`~c4g_client.NotFound` as REST's 404. The first set is
fetched before the call returns, so a bad request fails at the call, as REST's does.
"""

from __future__ import annotations

from typing import Any, AsyncIterator, Iterator, List, Optional, Sequence, Tuple
from urllib.parse import urlsplit

from . import _c4gs
from ._approx import Keyframes, KeyframesLike, Prune, PruneLike
from ._c4gv import C4GVDecoder
from ._errors import C4GError, TransportError, grpc_api_error
from ._sets import GaussianSet

METHOD = "/c4g.v1.C4G/StreamGaussians"
DECODE_METHOD = "/c4g.v1.C4G/Decode"
KIND_KEY = "c4g-error-kind"

_QUALITY = {"exact": 1, "balanced": 2, "fast": 3}
_PRECISION = {"f32": 1, "f16": 2}
_PRECISION_NAMES = {0: "f32", 1: "f32", 2: "f16"}


def _modules() -> Tuple[Any, Any]:
    try:
        import grpc

        from ._proto import c4g_pb2
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(f"gRPC streaming needs the grpc extra: pip install 'c4g-client[grpc]' ({e})") from e
    return grpc, c4g_pb2


def target_for(base_url: str) -> Tuple[str, bool]:
    """The channel target (``host:port``) of a base URL, and whether it is TLS."""
    parts = urlsplit(base_url)
    secure = parts.scheme == "https"
    port = parts.port or (443 if secure else 80)
    host = parts.hostname or ""
    if ":" in host:
        host = f"[{host}]"
    return f"{host}:{port}", secure


def stream_request(
    clip_id: str,
    *,
    start: Optional[float] = None,
    end: Optional[float] = None,
    step: Optional[float] = None,
    fps: Optional[float] = None,
    precision: str = "f32",
    quality: Optional[str] = None,
    keyframes: Optional[KeyframesLike] = None,
    prune: Optional[PruneLike] = None,
    compact: Optional[Tuple[float, int]] = None,
    scene: Optional[str] = None,
) -> Any:
    """The ``StreamGaussiansRequest`` for these options (``compact``: position error and
    keyframe interval, 0 for the server's defaults)."""
    _, pb = _modules()
    request = pb.StreamGaussiansRequest(clip_id=clip_id)
    if start is not None:
        request.start = start
    if end is not None:
        request.end = end
    if step is not None and fps is not None:
        raise ValueError("give step or fps, not both")
    if step is not None:
        request.step = step
    if fps is not None:
        request.fps = fps
    _set_decoding(pb, request, precision, quality, keyframes, prune, scene)
    if compact is not None:
        request.compact.CopyFrom(
            pb.CompactStream(position_error=compact[0], keyframe_interval=int(compact[1]))
        )
    return request


def decode_request(
    clip_id: str,
    times: Sequence[float],
    *,
    precision: str = "f32",
    quality: Optional[str] = None,
    keyframes: Optional[KeyframesLike] = None,
    prune: Optional[PruneLike] = None,
    features: bool = False,
    scene: Optional[str] = None,
) -> Any:
    """The ``DecodeRequest`` for these options."""
    _, pb = _modules()
    request = pb.DecodeRequest(clip_id=clip_id, times=[float(t) for t in times], features=features)
    _set_decoding(pb, request, precision, quality, keyframes, prune, scene)
    return request


def _set_decoding(
    pb: Any,
    request: Any,
    precision: str,
    quality: Optional[str],
    keyframes: Optional[KeyframesLike],
    prune: Optional[PruneLike],
    scene: Optional[str],
) -> None:
    """The fields ``StreamGaussiansRequest`` and ``DecodeRequest`` share, set on ``request``
    (``scene`` left out is the proto's empty string: ``auto``)."""
    if precision not in _PRECISION:
        raise ValueError(f"unknown precision {precision!r} (f32 or f16)")
    request.precision = _PRECISION[precision]
    if quality is not None:
        if quality not in _QUALITY:
            raise ValueError(f"unknown quality {quality!r} (exact, balanced or fast)")
        request.quality = _QUALITY[quality]
    if keyframes is not None:
        request.keyframes.CopyFrom(_keyframes(pb, keyframes))
    if prune is not None:
        fields = prune.to_json() if isinstance(prune, Prune) else dict(prune)
        request.prune.CopyFrom(pb.Prune(**fields))
    if scene is not None:
        request.scene = scene


def _keyframes(pb: Any, keyframes: KeyframesLike) -> Any:
    fields = keyframes.to_json() if isinstance(keyframes, Keyframes) else dict(keyframes)
    if "every_s" in fields:
        return pb.Keyframes(every_s=fields["every_s"])
    if "count" in fields:
        return pb.Keyframes(count=fields["count"])
    adaptive = {
        k: fields[k] for k in ("tolerance", "color_tolerance", "max", "min_interval_s") if k in fields
    }
    return pb.Keyframes(adaptive=pb.AdaptiveKeyframes(**adaptive))


def metadata_for(api_key: Optional[str]) -> List[Tuple[str, str]]:
    return [("authorization", f"Bearer {api_key}")] if api_key else []


def error_from(error: Any) -> C4GError:
    """The exception for a failed call: the server's kind when it sent one; a connection that
    never opened is a :class:`TransportError`."""
    code = error.code().name if hasattr(error, "code") and error.code() is not None else "UNKNOWN"
    details = error.details() if hasattr(error, "details") else str(error)
    kind = None
    try:
        for key, value in error.trailing_metadata() or ():
            if key == KIND_KEY:
                kind = value
    except Exception:  # noqa: BLE001 - a status without metadata
        kind = None
    if kind is None and code == "UNAVAILABLE":
        return TransportError(f"gRPC: {details}")
    return grpc_api_error(code, details or "", kind)


def set_of(frame: Any) -> GaussianSet:
    """The set of a ``GaussianFrame`` whose ``gaussians`` are packed columns (with their
    features when ``feature_width`` is above 0)."""
    g = frame.gaussians
    precision = _PRECISION_NAMES.get(g.precision, "f32")
    columns = [g.means, g.scales, g.rotations, g.opacities, g.colors]
    return _c4gs.unpack_columns(frame.time, g.count, precision, columns, g.features, g.feature_width)


#: A ``Decode`` answer is every set in one message: 10 sets of c4g-tiny with features are 2.9
#: MB, past grpcio's default 4 MiB receive limit at 14 sets, so the client takes what it asked for.
#: One channel carries every call, so the limit is the channel's.
_CHANNEL_OPTIONS = [("grpc.max_receive_message_length", -1)]


def open_channel(base_url: str, aio: bool = False) -> Any:
    """A channel to the server at ``base_url`` (``grpc.aio``'s with ``aio``), for a client to
    keep: it connects on its first call."""
    grpc, _ = _modules()
    target, secure = target_for(base_url)
    module = grpc.aio if aio else grpc
    if secure:
        return module.secure_channel(target, grpc.ssl_channel_credentials(), options=_CHANNEL_OPTIONS)
    return module.insecure_channel(target, options=_CHANNEL_OPTIONS)


def decode(channel: Any, api_key: Optional[str], request: Any) -> List[GaussianSet]:
    """The sets of a ``Decode`` call on ``channel``, in the order of the request's times."""
    grpc, pb = _modules()
    method = channel.unary_unary(
        DECODE_METHOD,
        request_serializer=pb.DecodeRequest.SerializeToString,
        response_deserializer=pb.DecodeResponse.FromString,
    )
    try:
        response = method(request, metadata=metadata_for(api_key))
    except grpc.RpcError as e:
        raise error_from(e) from None
    return [set_of(frame) for frame in response.frames]


async def adecode(channel: Any, api_key: Optional[str], request: Any) -> List[GaussianSet]:
    """:func:`decode` for asyncio, on a ``grpc.aio`` channel."""
    grpc, pb = _modules()
    method = channel.unary_unary(
        DECODE_METHOD,
        request_serializer=pb.DecodeRequest.SerializeToString,
        response_deserializer=pb.DecodeResponse.FromString,
    )
    try:
        response = await method(request, metadata=metadata_for(api_key))
    except grpc.RpcError as e:
        raise error_from(e) from None
    return [set_of(frame) for frame in response.frames]


class _Frames:
    """Turns the stream's messages into sets: packed columns, or pieces of one C4GV stream; and
    keeps the scene the messages say serves the stream."""

    def __init__(self, compact: bool) -> None:
        self._decoder = C4GVDecoder() if compact else None
        self.scene: Optional[str] = None

    def push(self, message: Any) -> List[GaussianSet]:
        self.scene = message.scene or self.scene
        if self._decoder is None:
            return [set_of(message)]
        self._decoder.feed(message.c4gv)
        return list(self._decoder.frames())

    def finish(self) -> None:
        if self._decoder is not None:
            self._decoder.finish()


class GrpcSetStream:
    """Sets in time order from a ``StreamGaussians`` call on the client's channel (close it, or
    use ``with``, to stop early: the server stops decoding; the channel stays the client's)."""

    def __init__(self, channel: Any, api_key: Optional[str], request: Any, compact: bool) -> None:
        grpc, pb = _modules()
        self._grpc = grpc
        method = channel.unary_stream(
            METHOD,
            request_serializer=pb.StreamGaussiansRequest.SerializeToString,
            response_deserializer=pb.GaussianFrame.FromString,
        )
        self._call = method(request, metadata=metadata_for(api_key))
        self._frames = _Frames(compact)
        self._pending: List[GaussianSet] = []
        self._ended = False
        try:
            self._fill()
        except BaseException:
            self.close()
            raise

    def _fill(self) -> None:
        """Reads messages until a set is pending or the stream ends."""
        while not self._pending and not self._ended:
            try:
                message = next(self._call)
            except StopIteration:
                self._ended = True
                self._frames.finish()
                return
            except self._grpc.RpcError as e:
                self._ended = True
                raise error_from(e) from None
            self._pending.extend(self._frames.push(message))

    @property
    def scene(self) -> Optional[str]:
        """The scene that serves the stream (``feed-forward`` or ``fitted``), once its first
        message arrived (the call waits for it)."""
        return self._frames.scene

    def __iter__(self) -> Iterator[GaussianSet]:
        return self

    def __next__(self) -> GaussianSet:
        try:
            self._fill()
        except BaseException:
            self.close()
            raise
        if not self._pending:
            self.close()
            raise StopIteration
        return self._pending.pop(0)

    def close(self) -> None:
        """Cancels the call (if still running)."""
        self._call.cancel()

    def __enter__(self) -> GrpcSetStream:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class AsyncGrpcSetStream:
    """:class:`GrpcSetStream` for asyncio (``grpc.aio``); make one with
    :meth:`AsyncClient.grpc_stream <c4g_client.AsyncClient.grpc_stream>`."""

    def __init__(self, channel: Any, api_key: Optional[str], request: Any, compact: bool) -> None:
        grpc, pb = _modules()
        self._grpc = grpc
        method = channel.unary_stream(
            METHOD,
            request_serializer=pb.StreamGaussiansRequest.SerializeToString,
            response_deserializer=pb.GaussianFrame.FromString,
        )
        self._call = method(request, metadata=metadata_for(api_key))
        self._messages = self._call.__aiter__()
        self._frames = _Frames(compact)
        self._pending: List[GaussianSet] = []
        self._ended = False

    async def _fill(self) -> None:
        while not self._pending and not self._ended:
            try:
                message = await self._messages.__anext__()
            except StopAsyncIteration:
                self._ended = True
                self._frames.finish()
                return
            except self._grpc.RpcError as e:
                self._ended = True
                raise error_from(e) from None
            self._pending.extend(self._frames.push(message))

    @property
    def scene(self) -> Optional[str]:
        """The scene that serves the stream, once its first message arrived (after
        :meth:`start`)."""
        return self._frames.scene

    async def start(self) -> AsyncGrpcSetStream:
        """Waits for the first set (so a bad request fails here)."""
        try:
            await self._fill()
        except BaseException:
            await self.aclose()
            raise
        return self

    def __aiter__(self) -> AsyncIterator[GaussianSet]:
        return self

    async def __anext__(self) -> GaussianSet:
        try:
            await self._fill()
        except BaseException:
            await self.aclose()
            raise
        if not self._pending:
            await self.aclose()
            raise StopAsyncIteration
        return self._pending.pop(0)

    async def aclose(self) -> None:
        """Cancels the call (if still running)."""
        self._call.cancel()

    async def __aenter__(self) -> AsyncGrpcSetStream:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()
