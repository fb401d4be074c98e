"""PNG in and out with NumPy and the standard library, so images need no imaging package.

Reading: the server's renders and context frames are 8-bit RGB PNGs; this reads any
non-interlaced 8-bit greyscale, grey+alpha, RGB or RGBA PNG into an ``(H, W, C)`` ``uint8``
array. The None, Sub and Up row filters are vectorised; Average and Paeth depend on the pixel to
the left, so they run as a loop over a row's bytes (the server filters with Paeth: about 0.1 s
for a 256² render). Where Pillow is importable it decodes instead (the same pixels, in C), and
``pure=True`` forces this reader (the tests compare the two).

Writing: uploads of NumPy frames and the notebook display of depth maps need PNG bytes; rows
are written unfiltered and deflated, which is all a lossless upload needs.
"""

from __future__ import annotations

import io
import struct
import zlib
from typing import List

import numpy as np

from ._errors import FormatError

SIGNATURE = b"\x89PNG\r\n\x1a\n"
_CHANNELS = {0: 1, 2: 3, 4: 2, 6: 4}


def encode(array: np.ndarray) -> bytes:
    """PNG bytes of an ``(H, W)``, ``(H, W, 1)``, ``(H, W, 3)`` or ``(H, W, 4)`` ``uint8``
    array."""
    a = np.asarray(array)
    if a.dtype != np.uint8:
        raise ValueError(f"a PNG frame is uint8; got {a.dtype} (scale and convert it first)")
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4) or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"a PNG frame is (H, W), (H, W, 3) or (H, W, 4); got {a.shape}")
    height, width, channels = a.shape
    color_type = {1: 0, 3: 2, 4: 6}[channels]
    rows = np.zeros((height, 1 + width * channels), dtype=np.uint8)
    rows[:, 1:] = np.ascontiguousarray(a).reshape(height, width * channels)
    header = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    return (
        SIGNATURE
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(rows.tobytes(), 6))
        + _chunk(b"IEND", b"")
    )


def decode(data: bytes, *, pure: bool = False) -> np.ndarray:
    """The ``(H, W, C)`` ``uint8`` pixels of PNG bytes (C = 1, 2, 3 or 4)."""
    if not pure:
        try:
            from PIL import Image
        except ImportError:
            pass
        else:
            with Image.open(io.BytesIO(data)) as image:
                a = np.asarray(image)
            return a[:, :, None] if a.ndim == 2 else a
    return _decode_pure(data)


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _decode_pure(data: bytes) -> np.ndarray:
    if not data.startswith(SIGNATURE):
        raise FormatError("not a PNG (no PNG signature)")
    at = len(SIGNATURE)
    header = None
    idat: List[bytes] = []
    while at + 8 <= len(data):
        (length,) = struct.unpack_from(">I", data, at)
        kind = data[at + 4 : at + 8]
        body = data[at + 8 : at + 8 + length]
        if len(body) != length:
            raise FormatError("a truncated PNG")
        at += 12 + length
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if header is None:
        raise FormatError("a PNG without IHDR")
    width, height, depth, color_type, _, _, interlace = header
    if depth != 8 or color_type not in _CHANNELS or interlace != 0:
        raise FormatError(
            f"this reader takes 8-bit non-interlaced PNGs; got depth {depth}, colour type "
            f"{color_type}, interlace {interlace} (install Pillow for others)"
        )
    channels = _CHANNELS[color_type]
    stride = width * channels
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as e:
        raise FormatError(f"corrupt PNG data ({e})") from None
    if len(raw) != height * (stride + 1):
        raise FormatError("PNG data does not match its size")
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(height, stride + 1)
    out = np.zeros((height, stride), dtype=np.uint8)
    previous = np.zeros(stride, dtype=np.uint8)
    for y in range(height):
        kind, line = rows[y, 0], rows[y, 1:]
        if kind == 0:
            current = line.copy()
        elif kind == 1:
            # Sub: each byte adds the reconstructed byte one pixel left, a running sum per channel.
            sums = np.cumsum(line.reshape(width, channels).astype(np.uint64), axis=0)
            current = (sums % 256).astype(np.uint8).reshape(stride)
        elif kind == 2:
            current = line + previous
        elif kind in (3, 4):
            current = _sequential(int(kind), line, previous, channels)
        else:
            raise FormatError(f"unknown PNG row filter {kind}")
        out[y] = current
        previous = current
    return out.reshape(height, width, channels)


def _sequential(kind: int, line: np.ndarray, previous: np.ndarray, bpp: int) -> np.ndarray:
    """Average (3) or Paeth (4) unfiltering of one row: each byte needs the one left of it."""
    filt = line.tolist()
    up = previous.tolist()
    cur = [0] * len(filt)
    for i, x in enumerate(filt):
        a = cur[i - bpp] if i >= bpp else 0
        b = up[i]
        if kind == 3:
            cur[i] = (x + ((a + b) >> 1)) & 0xFF
            continue
        c = up[i - bpp] if i >= bpp else 0
        pa = abs(b - c)
        pb = abs(a - c)
        pc = abs(a + b - c - c)
        if pa <= pb and pa <= pc:
            pred = a
        elif pb <= pc:
            pred = b
        else:
            pred = c
        cur[i] = (x + pred) & 0xFF
    return np.array(cur, dtype=np.uint8)
