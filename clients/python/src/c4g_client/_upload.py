"""Upload bodies (``POST /v1/clips``): a video or an image archive as the raw body, or image
frames as a ``multipart/form-data`` body of ``frame`` parts.

The body is described up front as a list of pieces (bytes in memory, or a file to read) with a
known total, then streamed in chunks, each chunk advancing the caller's ``progress(sent,
total)``: a progress bar moves while the bytes go out, then waits at 100% while the server
encodes (the answer comes once the clip is ready). The multipart body is written here rather
than by httpx so that it streams from the files with progress, and its length is known.

Sources: a path to a video or archive (sent as the body, its content type from the extension);
a path to a folder of PNG/JPEG frames, one image, or a list of image paths (multipart, frames
in name order for a folder, else as given); ``bytes`` (the
body; the server sniffs what it is); or a sequence of ``(H, W, 3)`` ``uint8`` arrays, encoded as
PNG frames here, with their ``times`` sent as the ``timestamps`` option.
"""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any, AsyncIterator, Callable, Dict, Iterator, List, Optional, Sequence, Tuple, Union

import numpy as np

from . import _png

#: Bytes per chunk: small enough that progress moves smoothly, large enough not to matter.
CHUNK = 256 * 1024

Progress = Callable[[int, int], Any]
Piece = Union[bytes, Path]
UploadSource = Union[
    str, "os.PathLike[str]", bytes, Sequence[np.ndarray], Sequence[Union[str, "os.PathLike[str]"]]
]

_VIDEO_TYPES = {
    ".mp4": "video/mp4",
    ".m4v": "video/mp4",
    ".mov": "video/quicktime",
    ".mkv": "video/x-matroska",
    ".webm": "video/webm",
    ".avi": "video/x-msvideo",
    ".gif": "image/gif",
    ".zip": "application/zip",
    ".tar": "application/x-tar",
}
_IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


@dataclass
class UploadBody:
    """A body to stream: its content type, pieces and total length."""

    content_type: str
    pieces: List[Piece]
    query: Dict[str, str]

    @property
    def total(self) -> int:
        return sum(len(p) if isinstance(p, bytes) else p.stat().st_size for p in self.pieces)

    def chunks(self, progress: Optional[Progress]) -> Iterator[bytes]:
        """The body in chunks, calling ``progress(sent, total)`` first with 0, then per chunk."""
        total = self.total
        sent = 0
        if progress:
            progress(0, total)
        for piece in self.pieces:
            for chunk in _piece_chunks(piece):
                sent += len(chunk)
                yield chunk
                if progress:
                    progress(sent, total)

    async def achunks(self, progress: Optional[Progress]) -> AsyncIterator[bytes]:
        """:meth:`chunks` for an async client (file reads are short blocking reads)."""
        for chunk in self.chunks(progress):
            yield chunk


def options(
    *,
    fps: Optional[float] = None,
    times: Optional[Sequence[float]] = None,
    max_frames: Optional[int] = None,
    stride: Optional[int] = None,
    start: Optional[float] = None,
    end: Optional[float] = None,
) -> Dict[str, str]:
    """The upload options as the name-value pairs the query string and the form carry."""
    pairs: Dict[str, str] = {}
    if fps is not None:
        pairs["fps"] = repr(float(fps))
    if times is not None:
        pairs["timestamps"] = ",".join(repr(float(t)) for t in times)
    if max_frames is not None:
        pairs["max_frames"] = str(int(max_frames))
    if stride is not None:
        pairs["stride"] = str(int(stride))
    if start is not None:
        pairs["start"] = repr(float(start))
    if end is not None:
        pairs["end"] = repr(float(end))
    return pairs


def body_for(source: UploadSource, pairs: Dict[str, str], content_type: Optional[str]) -> UploadBody:
    """The body that uploads ``source`` with the options ``pairs`` (see the module doc)."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return UploadBody(content_type or "application/octet-stream", [bytes(source)], pairs)
    if isinstance(source, (str, os.PathLike)):
        path = Path(source)
        if path.is_dir():
            images = sorted(p for p in path.iterdir() if p.suffix.lower() in _IMAGE_TYPES and p.is_file())
            if not images:
                raise ValueError(f"{path} holds no .png or .jpg images to upload as frames")
            return _multipart([(p.name, _IMAGE_TYPES[p.suffix.lower()], p) for p in images], pairs)
        if not path.is_file():
            raise FileNotFoundError(f"no file or folder at {path}")
        if path.suffix.lower() in _IMAGE_TYPES:
            return _multipart([(path.name, _IMAGE_TYPES[path.suffix.lower()], path)], pairs)
        kind = content_type or _VIDEO_TYPES.get(path.suffix.lower(), "application/octet-stream")
        return UploadBody(kind, [path], pairs)
    frames: List[Any] = list(source)
    if not frames:
        raise ValueError("no frames to upload")
    if all(isinstance(f, (str, os.PathLike)) for f in frames):
        paths = [Path(f) for f in frames]
        for p in paths:
            if p.suffix.lower() not in _IMAGE_TYPES:
                raise ValueError(f"{p} is not a .png or .jpg frame")
        return _multipart([(p.name, _IMAGE_TYPES[p.suffix.lower()], p) for p in paths], pairs)
    parts: List[Tuple[str, str, Piece]] = []
    for k, frame in enumerate(frames):
        a = np.asarray(frame)
        if a.ndim != 3 or a.shape[2] != 3 or a.dtype != np.uint8:
            raise ValueError(f"frame {k} must be an (H, W, 3) uint8 array; got {a.shape} {a.dtype}")
        parts.append((f"frame-{k:05d}.png", "image/png", _png.encode(a)))
    return _multipart(parts, pairs)


def _multipart(parts: List[Tuple[str, str, Piece]], pairs: Dict[str, str]) -> UploadBody:
    """A form: the options as text fields first (so a streaming parser has them before the
    frames), then one ``frame`` part per image."""
    boundary = "c4g-" + uuid.uuid4().hex
    pieces: List[Piece] = []
    for name, value in pairs.items():
        pieces.append(
            f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"\r\n\r\n{value}\r\n'.encode()
        )
    for filename, kind, piece in parts:
        safe = filename.replace('"', "_").replace("\r", "_").replace("\n", "_")
        pieces.append(
            (
                f'--{boundary}\r\nContent-Disposition: form-data; name="frame"; '
                f'filename="{safe}"\r\nContent-Type: {kind}\r\n\r\n'
            ).encode()
        )
        pieces.append(piece)
        pieces.append(b"\r\n")
    pieces.append(f"--{boundary}--\r\n".encode())
    return UploadBody(f"multipart/form-data; boundary={boundary}", pieces, {})


def _piece_chunks(piece: Piece) -> Iterator[bytes]:
    if isinstance(piece, bytes):
        for at in range(0, len(piece), CHUNK):
            yield piece[at : at + CHUNK]
        return
    with open(piece, "rb") as f:
        while True:
            chunk = f.read(CHUNK)
            if not chunk:
                return
            yield chunk
