"""``C4GS``, the server's packed binary Gaussian sets (``renderer/src/formats/c4gs.rs`` is the
specification; ``docs/api.md``, format ``binary``), read into :class:`GaussianSet`.

Little endian: a 16-byte header (``b"C4GS"``, ``u16`` version 1, ``u8`` precision 0 f32 / 1 f16,
``u8`` reserved, ``u32`` frames, ``u32`` N), then per frame an ``f64`` time and the columns means
(N×3), scales (N×3), rotations (N×4, w x y z), opacities (N), colours (N×3) in the precision.
The same columns are the arrays of gRPC's ``GaussianSet`` message, so :func:`unpack_columns`
serves both. Decoding is a NumPy view per column: no per-value Python work. Every length is
checked against the header before anything is read, so a short or hostile payload is a
:class:`FormatError`, never a huge allocation.
"""

from __future__ import annotations

import struct
from typing import Dict, List, Sequence, Tuple

import numpy as np

from ._errors import FormatError
from ._sets import WIRE_COLUMNS, GaussianSet, from_columns

MAGIC = b"C4GS"
VERSION = 1
HEADER_BYTES = 16
_VALUES_PER_GAUSSIAN = sum(width for _, width in WIRE_COLUMNS)
#: Wire precision name → (header code, little-endian dtype).
PRECISIONS: Dict[str, Tuple[int, np.dtype]] = {"f32": (0, np.dtype("<f4")), "f16": (1, np.dtype("<f2"))}
_BY_CODE = {code: (name, dtype) for name, (code, dtype) in PRECISIONS.items()}


def decode(payload: bytes) -> List[GaussianSet]:
    """The frames of a ``C4GS`` payload, in order, as ``float32`` sets."""
    if len(payload) < HEADER_BYTES:
        raise FormatError(
            f"a C4GS payload starts with a {HEADER_BYTES}-byte header; got {len(payload)} bytes"
        )
    magic, version, code, _reserved, frames, count = struct.unpack_from("<4sHBBII", payload)
    if magic != MAGIC:
        raise FormatError(f"not a C4GS payload (starts with {magic!r})")
    if version != VERSION:
        raise FormatError(f"C4GS version {version}; this reader reads version {VERSION} only")
    if code not in _BY_CODE:
        raise FormatError(f"unknown C4GS precision code {code}")
    name, dtype = _BY_CODE[code]
    frame_bytes = 8 + count * _VALUES_PER_GAUSSIAN * dtype.itemsize
    expected = HEADER_BYTES + frames * frame_bytes
    if len(payload) != expected:
        raise FormatError(
            f"C4GS payload of {frames} frames of {count} {name} Gaussians needs {expected} "
            f"bytes; got {len(payload)}"
        )
    sets = []
    for k in range(frames):
        at = HEADER_BYTES + k * frame_bytes
        (time,) = struct.unpack_from("<d", payload, at)
        at += 8
        columns = []
        for _, width in WIRE_COLUMNS:
            size = count * width * dtype.itemsize
            columns.append(payload[at : at + size])
            at += size
        sets.append(unpack_columns(time, count, name, columns))
    return sets


def unpack_columns(time: float, count: int, precision: str, columns: Sequence[bytes]) -> GaussianSet:
    """The set of ``count`` Gaussians in five packed columns (means, scales, rotations,
    opacities, colours) of ``precision`` (``"f32"`` or ``"f16"``), each length checked."""
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
    return from_columns(time, arrays)
