"""``C4GS``, the server's packed binary Gaussian sets (``formats/src/c4gs.rs`` is the
specification; ``docs/api.md``, format ``binary``), read into :class:`GaussianSet`.

Little endian: a 16-byte header (``b"C4GS"``, ``u16`` version, ``u8`` precision 0 f32 / 1 f16,
``u8`` reserved, ``u32`` frames, ``u32`` N), then per frame an ``f64`` time and the columns means
(N×3), scales (N×3), rotations (N×4, w x y z), opacities (N), colours (N×3) in the precision.

Version 1 has no features. Version 2 is a decode that asked for them (``"features": true``):
version 1's header with version 2, then a ``u32`` F (floats per feature vector, at least 1), and
per frame a sixth column after the colours, the features (N×F, row i Gaussian i's vector), in
the precision. The server writes version 1 whenever there are no features, so both are read
here, each by its own layout.

The same columns are the arrays of gRPC's ``GaussianSet`` message (``feature_width`` and
``features`` its sixth), so :func:`unpack_columns` serves both. Decoding is a NumPy view per
column: no per-value Python work. Every length is checked against the header before anything
is read, so a short or hostile payload is a :class:`FormatError`, never a huge allocation.
"""

from __future__ import annotations

import struct
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

from ._errors import FormatError
from ._sets import WIRE_COLUMNS, GaussianSet, from_columns

MAGIC = b"C4GS"
#: The version of payloads without features.
VERSION = 1
#: The version of payloads with features: a feature width after the header, a feature column
#: after the colours.
VERSION_FEATURES = 2
HEADER_BYTES = 16
#: Bytes of version 2's feature width, after the header.
FEATURE_WIDTH_BYTES = 4
_VALUES_PER_GAUSSIAN = sum(width for _, width in WIRE_COLUMNS)
#: Wire precision name → (header code, little-endian dtype).
PRECISIONS: Dict[str, Tuple[int, np.dtype]] = {"f32": (0, np.dtype("<f4")), "f16": (1, np.dtype("<f2"))}
_BY_CODE = {code: (name, dtype) for name, (code, dtype) in PRECISIONS.items()}


def decode(payload: bytes) -> List[GaussianSet]:
    """The frames of a ``C4GS`` payload (version 1 or 2), in order, as ``float32`` sets; those
    of version 2 carry their ``features``."""
    if len(payload) < HEADER_BYTES:
        raise FormatError(
            f"a C4GS payload starts with a {HEADER_BYTES}-byte header; got {len(payload)} bytes"
        )
    magic, version, code, _reserved, frames, count = struct.unpack_from("<4sHBBII", payload)
    if magic != MAGIC:
        raise FormatError(f"not a C4GS payload (starts with {magic!r})")
    if version not in (VERSION, VERSION_FEATURES):
        raise FormatError(
            f"C4GS version {version}; this reader reads versions {VERSION} and {VERSION_FEATURES}"
        )
    if code not in _BY_CODE:
        raise FormatError(f"unknown C4GS precision code {code}")
    name, dtype = _BY_CODE[code]
    width, header_bytes = 0, HEADER_BYTES
    if version == VERSION_FEATURES:
        if len(payload) < HEADER_BYTES + FEATURE_WIDTH_BYTES:
            raise FormatError(
                f"a C4GS version 2 payload has its feature width after the header; got {len(payload)} bytes"
            )
        (width,) = struct.unpack_from("<I", payload, HEADER_BYTES)
        if width == 0:
            raise FormatError("a C4GS version 2 payload's feature width is at least 1; got 0")
        header_bytes += FEATURE_WIDTH_BYTES
    # Python's integers do not overflow, so a hostile header only makes `expected` large, and
    # the payload's own length then refuses it before anything is read.
    frame_bytes = 8 + count * (_VALUES_PER_GAUSSIAN + width) * dtype.itemsize
    expected = header_bytes + frames * frame_bytes
    if len(payload) != expected:
        with_features = f" with {width} feature channels" if width else ""
        raise FormatError(
            f"C4GS payload of {frames} frames of {count} {name} Gaussians{with_features} needs "
            f"{expected} bytes; got {len(payload)}"
        )
    sets = []
    for k in range(frames):
        at = header_bytes + k * frame_bytes
        (time,) = struct.unpack_from("<d", payload, at)
        at += 8
        columns = []
        for _, column_width in WIRE_COLUMNS:
            size = count * column_width * dtype.itemsize
            columns.append(payload[at : at + size])
            at += size
        features = payload[at : at + count * width * dtype.itemsize] if width else None
        sets.append(unpack_columns(time, count, name, columns, features, width))
    return sets


def unpack_columns(
    time: float,
    count: int,
    precision: str,
    columns: Sequence[bytes],
    features: Optional[bytes] = None,
    feature_width: int = 0,
) -> GaussianSet:
    """The set of ``count`` Gaussians in five packed columns (means, scales, rotations,
    opacities, colours) of ``precision`` (``"f32"`` or ``"f16"``), each length checked; with
    ``feature_width`` F above 0, ``features`` is a sixth column of N×F values (gRPC sends an
    empty one and width 0 for a set without them)."""
    if precision not in PRECISIONS:
        raise FormatError(f"unknown precision {precision!r} (f32 or f16)")
    dtype = PRECISIONS[precision][1]
    arrays = []
    for (name, width), column in zip(WIRE_COLUMNS, columns):
        expected = count * width * dtype.itemsize
        if len(column) != expected:
            raise FormatError(
                f"{name} of {count} {precision} Gaussians needs {expected} bytes; got {len(column)}"
            )
        arrays.append(np.frombuffer(column, dtype=dtype).astype(np.float32))
    if feature_width == 0:
        if features:
            raise FormatError(f"{len(features)} bytes of features with a feature width of 0")
        return from_columns(time, arrays)
    expected = count * feature_width * dtype.itemsize
    if features is None or len(features) != expected:
        raise FormatError(
            f"features of {count} {precision} Gaussians of width {feature_width} need {expected} "
            f"bytes; got {0 if features is None else len(features)}"
        )
    values = np.frombuffer(features, dtype=dtype).astype(np.float32)
    return from_columns(time, arrays, values, feature_width)
