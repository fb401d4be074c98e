"""``C4GV``, the compact 4D stream (``POST /v1/clips/{id}/stream``, gRPC ``StreamGaussians``
with ``compact``), decoded incrementally: feed bytes as they arrive, take each set as soon as its
record is whole.

The specification is the module doc of ``formats/src/c4gv/mod.rs``; this reader follows its
"Reading" section, step by step, and the Rust ``Decoder``'s checks. In short (little endian): a
header (``b"C4GV"``, ``u16`` version 1, ``u8`` predictor 0, ``u8`` reserved, ``u32`` N, ``u32`` S
static Gaussians, five ``f64`` grid steps, the ⌈N/8⌉-byte static mask), then records, each a
6-byte head (``u8`` kind 1 static / 2 keyframe / 3 delta / 4 index, ``u8`` coding 0 stored /
1 raw DEFLATE, ``u32`` length) and its payload: the static record once, the frames (``f64``
time, ``u32`` inflated length, body), and the index, which ends the stream. A body is 14 columns
(position xyz, scale xyz, rotation wxyz, opacity, colour RGB) of zigzag LEB128 varints, one per
Gaussian of the record: grid cells in the static record and keyframes, each cell's change from
the frame before in a delta frame.

Why the values are the Rust decoder's bit for bit: every value is computed as the spec says, in
``float64`` and then rounded to ``float32``, with the same operations in the same order
(``x*x + y*y + ...`` left to right for a quaternion's norm; IEEE multiply, divide and sqrt are
correctly rounded in both). The one transcendental, ``exp`` of a log-scale cell, is the C
library's ``exp``, the same function Rust's ``f64::exp`` calls on Linux, rounded to ``float32``
(``_libm.exp_f32``: NumPy's ``exp`` where its last bit cannot matter, the C library's where it
could).

Everything is done with NumPy over a whole record at once (the varints too), so a set costs a
few dozen array operations, not 14·N Python steps (``benches/c4gv_read.py`` times it). Every
length is checked against what it can be before anything is buffered for it, so a truncated or
corrupt stream is a :class:`FormatError` that says what is wrong.
"""

from __future__ import annotations

import math
import struct
import zlib
from typing import Iterator, List, NamedTuple, Optional, Tuple

import numpy as np

from ._errors import FormatError, StreamInterrupted
from ._libm import exp_f32
from ._sets import GaussianSet

MAGIC = b"C4GV"
INDEX_MAGIC = b"C4GI"
VERSION = 1
HEADER_BYTES = 56
RECORD_HEAD = 6
FRAME_HEAD = 12
STATIC_HEAD = 4
INDEX_ENTRY = 17
INDEX_TAIL = 12
CHANNELS = 14
VARINT_MAX = 5
CELL_LIMIT = 1 << 30
ROTATION_NORM_TOLERANCE = 1e-3

KIND_STATIC = 1
KIND_KEYFRAME = 2
KIND_DELTA = 3
KIND_INDEX = 4
CODING_STORED = 0
CODING_DEFLATE = 1


class Steps(NamedTuple):
    """The grid steps a stream's header carries."""

    position: float
    log_scale: float
    rotation: float
    opacity: float
    color: float

    def per_channel(self) -> np.ndarray:
        """The step of each of a body's 14 columns, in column order."""
        return np.repeat(np.array(self, dtype=np.float64), (3, 3, 4, 1, 3))


class Header(NamedTuple):
    """What a stream's header says."""

    gaussians: int
    static_mask: np.ndarray
    steps: Steps

    @property
    def position_error(self) -> float:
        """The position bound the encoder promised: its step is 1.875 times the bound."""
        return self.steps.position / 1.875


class IndexEntry(NamedTuple):
    """One frame in the index record."""

    time: float
    offset: int
    keyframe: bool


class C4GVDecoder:
    """The incremental reader: :meth:`feed` it bytes, take whole frames with
    :meth:`next_frame` (``None`` while more bytes are needed, and after the index), and call
    :meth:`finish` when the bytes end to check that the stream was complete."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._read = 0
        self._position = 0
        self._stage = "header"
        self.header: Optional[Header] = None
        self._statics = np.zeros(0, dtype=np.int64)
        self._movers = np.zeros(0, dtype=np.int64)
        self._held: Optional[Tuple[np.ndarray, ...]] = None
        self._previous: Optional[np.ndarray] = None
        self._seen: List[IndexEntry] = []
        self.index: Optional[List[IndexEntry]] = None

    @property
    def done(self) -> bool:
        """Whether the index record has been read: the stream is complete."""
        return self._stage == "done"

    @property
    def frames_read(self) -> int:
        """Frames decoded so far."""
        return len(self._seen)

    def feed(self, data: bytes) -> None:
        """Takes the next bytes of the stream."""
        if self._read and self._read >= len(self._buffer) // 2:
            del self._buffer[: self._read]
            self._read = 0
        self._buffer += data

    def frames(self) -> Iterator[GaussianSet]:
        """Every frame whose record has arrived whole, in order."""
        while True:
            frame = self.next_frame()
            if frame is None:
                return
            yield frame

    def next_frame(self) -> Optional[GaussianSet]:
        """The next frame if its record has arrived whole; ``None`` otherwise."""
        while True:
            pending = memoryview(self._buffer)[self._read :]
            if self._stage == "header":
                parsed = _parse_header(pending)
                if parsed is None:
                    return None
                self._start(*parsed)
                continue
            if self._stage == "done":
                if len(pending):
                    raise FormatError(f"{len(pending)} bytes after the index record, which ends a stream")
                return None
            head = self._record_head(pending)
            if head is None:
                return None
            kind, coding, length = head
            if len(pending) < RECORD_HEAD + length:
                return None
            payload = bytes(pending[RECORD_HEAD : RECORD_HEAD + length])
            offset = self._position
            self._consume(RECORD_HEAD + length)
            if kind == KIND_STATIC:
                self._read_static(coding, payload)
            elif kind == KIND_INDEX:
                self._read_index(payload)
            else:
                return self._read_frame(offset, kind, coding, payload)

    def finish(self) -> None:
        """Raises unless the stream ended with its index record and nothing after it."""
        pending = len(self._buffer) - self._read
        if self._stage == "done":
            if pending:
                raise FormatError(f"{pending} bytes after the index record, which ends a stream")
            return
        if self._stage == "header":
            raise StreamInterrupted(f"truncated: the stream ended inside its header ({pending} bytes)")
        extra = f" and {pending} bytes of an incomplete record" if pending else ""
        raise StreamInterrupted(
            f"truncated: the stream ended after {len(self._seen)} frames{extra}, before its index record"
        )

    # -- records --------------------------------------------------------------------------

    def _start(self, header: Header, length: int) -> None:
        self.header = header
        ids = np.arange(header.gaussians, dtype=np.int64)
        self._statics = ids[header.static_mask]
        self._movers = ids[~header.static_mask]
        self._consume(length)
        self._stage = "static"

    def _consume(self, count: int) -> None:
        self._read += count
        self._position += count

    def _record_head(self, pending: memoryview) -> Optional[Tuple[int, int, int]]:
        """Kind, coding and payload length of the record at the read position, once its six
        bytes are here, with the length checked against what that kind can hold."""
        if len(pending) < RECORD_HEAD:
            return None
        kind, coding, length = struct.unpack_from("<BBI", pending)
        at = self._position
        if self._stage == "static" and kind == KIND_STATIC:
            low, high = _body_range(STATIC_HEAD, len(self._statics))
        elif self._stage == "frames" and kind in (KIND_KEYFRAME, KIND_DELTA):
            low, high = _body_range(FRAME_HEAD, len(self._movers))
        elif kind == KIND_INDEX:
            low = high = len(self._seen) * INDEX_ENTRY + INDEX_TAIL
        elif self._stage == "static" and kind in (KIND_KEYFRAME, KIND_DELTA):
            raise FormatError(f"the record at byte {at} is a frame, but the static record comes first")
        elif kind == KIND_STATIC:
            raise FormatError(f"a second static record at byte {at}")
        else:
            raise FormatError(f"unknown record kind {kind} at byte {at}")
        if coding > CODING_DEFLATE or (kind == KIND_INDEX and coding != CODING_STORED):
            raise FormatError(f"record at byte {at}: unknown body coding {coding}")
        if not low <= length <= high:
            need = f"it must hold {low}" if low == high else f"it must hold {low} to {high}"
            raise FormatError(f"record at byte {at} (kind {kind}) claims {length} bytes: {need}")
        return kind, coding, length

    def _read_static(self, coding: int, payload: bytes) -> None:
        what = "the static record"
        cells = _read_body(coding, payload, len(self._statics), what)
        _check_cells(cells, self._statics, what)
        assert self.header is not None
        self._held = _reconstruct(cells, self.header.steps, self._statics, what)
        self._stage = "frames"

    def _read_frame(self, offset: int, kind: int, coding: int, payload: bytes) -> GaussianSet:
        what = f"frame {len(self._seen)} (byte {offset})"
        (time,) = struct.unpack_from("<d", payload)
        _check_time(len(self._seen), time, self._seen[-1].time if self._seen else None)
        values = _read_body(coding, payload[8:], len(self._movers), what)
        keyframe = kind == KIND_KEYFRAME
        if keyframe:
            _check_cells(values, self._movers, what)
            cells = values
        else:
            if self._previous is None:
                raise FormatError(f"{what} is a delta frame, but no keyframe came before it")
            cells = self._previous + values
            _check_cells(cells, self._movers, what)
        assert self.header is not None and self._held is not None
        moving = _reconstruct(cells, self.header.steps, self._movers, what)
        frame = _assemble(time, self.header.gaussians, self._statics, self._held, self._movers, moving)
        _validate(frame, what)
        self._previous = cells
        self._seen.append(IndexEntry(time, offset, keyframe))
        return frame

    def _read_index(self, payload: bytes) -> None:
        entries = _parse_index(payload, self._position)
        if entries != self._seen:
            first = next(
                (k for k, (a, b) in enumerate(zip(entries, self._seen)) if a != b),
                min(len(entries), len(self._seen)),
            )
            raise FormatError(
                f"the index does not list the frames as they came (first difference at frame {first})"
            )
        self.index = entries
        self._stage = "done"


def decode(data: bytes) -> List[GaussianSet]:
    """The frames of a whole ``C4GV`` stream."""
    decoder = C4GVDecoder()
    decoder.feed(data)
    frames = list(decoder.frames())
    decoder.finish()
    return frames


# -- parsing helpers --------------------------------------------------------------------------


def _parse_header(pending: memoryview) -> Optional[Tuple[Header, int]]:
    """The header at the start of ``pending`` and its length; ``None`` while incomplete."""
    prefix = bytes(pending[:4])
    if prefix != MAGIC[: len(prefix)]:
        raise FormatError(f"not a C4GV stream (starts with {prefix!r})")
    if len(pending) < HEADER_BYTES:
        return None
    version, predictor, _reserved, gaussians, statics = struct.unpack_from("<HBBII", pending, 4)
    if version != VERSION:
        raise FormatError(f"C4GV version {version}; this reader reads version {VERSION} only")
    if predictor != 0:
        raise FormatError(f"unknown C4GV predictor {predictor} (version 1 has 0 only)")
    steps = Steps(*struct.unpack_from("<5d", pending, 16))
    for step in steps:
        if not (math.isfinite(step) and step > 0):
            raise FormatError(f"C4GV grid steps must be finite and positive; the header has {step}")
    if statics > gaussians:
        raise FormatError(f"C4GV header claims {statics} static Gaussians of {gaussians}")
    length = HEADER_BYTES + (gaussians + 7) // 8
    if len(pending) < length:
        return None
    mask_bytes = np.frombuffer(bytes(pending[HEADER_BYTES:length]), dtype=np.uint8)
    bits = np.unpackbits(mask_bytes, bitorder="little")
    if bits[gaussians:].any():
        raise FormatError("C4GV static mask sets bits past the last Gaussian")
    mask = bits[:gaussians].astype(bool)
    if int(mask.sum()) != statics:
        raise FormatError(f"C4GV header claims {statics} static Gaussians; its mask marks {int(mask.sum())}")
    return Header(gaussians, mask, steps), length


def _body_range(head: int, count: int) -> Tuple[int, int]:
    """Smallest and largest payload of a record with ``head`` bytes before a body of ``count``
    Gaussians: a deflated body may be far shorter than 14 bytes a Gaussian, but is empty only
    when there is nothing to send."""
    return head + (1 if count > 0 else 0), head + count * CHANNELS * VARINT_MAX


def _read_body(coding: int, payload: bytes, count: int, what: str) -> np.ndarray:
    """The ``(count, 14)`` int64 values of a body: ``u32`` inflated length, then the stored or
    deflated columns of zigzag varints."""
    (raw,) = struct.unpack_from("<I", payload)
    stored = payload[4:]
    low, high = count * CHANNELS, count * CHANNELS * VARINT_MAX
    if not low <= raw <= high:
        raise FormatError(
            f"{what}: a body of {count} Gaussians inflates to {low} to {high} bytes; it claims {raw}"
        )
    if coding == CODING_STORED:
        if len(stored) != raw:
            raise FormatError(f"{what}: a stored body of {raw} bytes holds {len(stored)}")
        body = stored
    else:
        body = _inflate(stored, raw, what)
    values = _varints(body, count * CHANNELS, what)
    return values.reshape(CHANNELS, count).T.copy()


def _inflate(stored: bytes, raw: int, what: str) -> bytes:
    """A raw DEFLATE stream that must fill ``stored`` exactly and give ``raw`` bytes."""
    if len(stored) >= raw:
        raise FormatError(
            f"{what}: a deflated body of {len(stored)} bytes is not shorter than its {raw} bytes inflated"
        )
    inflater = zlib.decompressobj(-15)
    try:
        out = inflater.decompress(stored, raw + 1)
    except zlib.error as e:
        raise FormatError(f"{what}: corrupt DEFLATE data ({e})") from None
    if len(out) != raw:
        more = "more than " if len(out) > raw else ""
        raise FormatError(f"{what}: the body inflates to {more}{len(out)} bytes; its record says {raw}")
    if not inflater.eof:
        raise FormatError(f"{what}: corrupt DEFLATE data (the stream does not end)")
    if inflater.unused_data:
        raise FormatError(f"{what}: {len(inflater.unused_data)} bytes after the DEFLATE stream")
    return out


def _varints(body: bytes, n: int, what: str) -> np.ndarray:
    """``n`` zigzag LEB128 varints of at most five bytes that fill ``body`` exactly, as int64.

    Byte by byte place rather than varint by varint: every varint's first byte at once, then
    its second byte for those that have one, and so on (at most five rounds). Most varints of a
    delta frame are one byte, so the later rounds touch few; a body of one-byte varints is
    its bytes."""
    data = np.frombuffer(body, dtype=np.uint8)
    if n == 0:
        if len(data):
            raise FormatError(f"{what}: {len(data)} bytes after the last value")
        return np.zeros(0, dtype=np.int64)
    ends = np.flatnonzero(data < 0x80)
    if len(ends) < n:
        raise FormatError(f"{what}: a varint is cut short or too long")
    ends = ends[:n]
    if len(data) == n:
        unsigned = data.astype(np.int64)
    else:
        starts = np.empty(n, dtype=np.int64)
        starts[0] = 0
        starts[1:] = ends[:-1] + 1
        extra = ends - starts
        if int(extra.max()) >= VARINT_MAX:
            raise FormatError(f"{what}: a varint is cut short or too long")
        used = int(ends[-1]) + 1
        if used != len(data):
            raise FormatError(f"{what}: {len(data) - used} bytes after the last value")
        unsigned = (data[starts] & 0x7F).astype(np.int64)
        longer = np.flatnonzero(extra)
        for place in range(1, VARINT_MAX):
            if not len(longer):
                break
            unsigned[longer] |= (data[starts[longer] + place] & 0x7F).astype(np.int64) << (7 * place)
            longer = longer[extra[longer] > place]
    return (unsigned >> 1) ^ -(unsigned & 1)


def _check_cells(cells: np.ndarray, ids: np.ndarray, what: str) -> None:
    bad = np.abs(cells) >= CELL_LIMIT
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise FormatError(f"{what}: Gaussian {int(ids[row])}'s cell {int(cells[row, col])} is outside ±2^30")


def _check_time(frame: int, time: float, last: Optional[float]) -> None:
    if not math.isfinite(time):
        raise FormatError(f"frame {frame}: time {time} is not finite")
    if last is not None and time <= last:
        raise FormatError(
            f"frame {frame}: time {time} is not after the frame before's ({last}): frames come "
            "in strictly increasing time"
        )


def _reconstruct(
    cells: np.ndarray, steps: Steps, ids: np.ndarray, what: str
) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The values of ``(k, 14)`` cells: means, quats, scales, opacities, colours (float32).
    Every cell times its channel's step in one product (``float64``, as the spec says)."""
    products = cells * steps.per_channel()
    narrow = products.astype(np.float32)
    scales = exp_f32(products[:, 3:6])
    q = products[:, 6:10]
    squares = q * q
    norm = np.sqrt(squares[:, 0] + squares[:, 1] + squares[:, 2] + squares[:, 3])
    bad = ~(np.isfinite(norm) & (norm != 0.0))
    if bad.any():
        i = int(ids[np.flatnonzero(bad)[0]])
        raise FormatError(
            f"{what}: Gaussian {i}'s rotation decodes to no unit quaternion (zero or not finite)"
        )
    quats = (q / norm[:, None]).astype(np.float32)
    means, opacities, colors = narrow[:, 0:3].copy(), narrow[:, 10].copy(), narrow[:, 11:14].copy()
    return means, quats, scales, opacities, colors


def _assemble(
    time: float,
    count: int,
    statics: np.ndarray,
    held: Tuple[np.ndarray, ...],
    movers: np.ndarray,
    moving: Tuple[np.ndarray, ...],
) -> GaussianSet:
    """The whole set: the moving Gaussians' values among the held static ones, in Gaussian
    order. A stream without static Gaussians (every feed-forward one) is its moving values as
    they are: each frame's arrays are its own, made by :func:`_reconstruct`."""
    if not len(statics):
        return GaussianSet(float(time), *moving)
    widths = (3, 4, 3, 1, 3)
    columns = []
    for width, fixed, changing in zip(widths, held, moving):
        shape = (count,) if width == 1 else (count, width)
        column = np.empty(shape, dtype=np.float32)
        column[statics] = fixed
        column[movers] = changing
        columns.append(column)
    means, quats, scales, opacities, colors = columns
    return GaussianSet(float(time), means, quats, scales, opacities, colors)


def _validate(s: GaussianSet, what: str) -> None:
    """The canonical layout's invariants (``GaussianSet::validate``), which the Rust decoder
    holds every decoded set to: so a hostile stream gives valid sets or an error.

    A whole-array test first (a NaN fails every comparison, so the extremes catch it too), and
    the Gaussian-by-Gaussian one only to say which Gaussian broke which invariant."""
    norm = np.sqrt(
        s.quats[:, 0] * s.quats[:, 0]
        + s.quats[:, 1] * s.quats[:, 1]
        + s.quats[:, 2] * s.quats[:, 2]
        + s.quats[:, 3] * s.quats[:, 3]
    )
    if not len(s) or (
        np.isfinite(s.means).all()
        and s.scales.min() >= 0
        and s.scales.max() < math.inf
        and np.abs(norm - 1).max() <= ROTATION_NORM_TOLERANCE
        and s.opacities.min() >= 0
        and s.opacities.max() <= 1
        and s.colors.min() >= 0
        and s.colors.max() < math.inf
    ):
        return
    checks = [
        (np.isfinite(s.means).all(axis=1), "a position is not finite"),
        ((np.isfinite(s.scales) & (s.scales >= 0)).all(axis=1), "a scale is not finite and non-negative"),
        (np.abs(norm - 1) <= ROTATION_NORM_TOLERANCE, "a rotation is not a unit quaternion"),
        ((s.opacities >= 0) & (s.opacities <= 1), "an opacity is outside [0, 1]"),
        ((np.isfinite(s.colors) & (s.colors >= 0)).all(axis=1), "a colour is not finite and non-negative"),
    ]
    for ok, reason in checks:
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            raise FormatError(f"{what} decodes to an invalid set: Gaussian {i}: {reason}")


def _parse_index(payload: bytes, end: int) -> List[IndexEntry]:
    """The index record's entries, checked: times finite and increasing, offsets increasing and
    before the record (which ends at ``end``), the first a keyframe."""
    entries, tail = payload[:-INDEX_TAIL], payload[-INDEX_TAIL:]
    if tail[8:] != INDEX_MAGIC:
        raise FormatError("the index record does not end with C4GI")
    (own,) = struct.unpack_from("<Q", tail)
    expected = max(0, end - (RECORD_HEAD + len(payload)))
    if own != expected:
        raise FormatError(f"the index record says it starts at byte {own}; it starts at {expected}")
    out: List[IndexEntry] = []
    for k in range(len(entries) // INDEX_ENTRY):
        time, offset, flag = struct.unpack_from("<dQB", entries, k * INDEX_ENTRY)
        if flag not in (0, 1):
            raise FormatError(f"index entry {k}: keyframe flag {flag} (0 or 1)")
        try:
            _check_time(k, time, out[-1].time if out else None)
        except FormatError as e:
            raise FormatError(f"the index: {e}") from None
        previous = out[-1].offset if out else 0
        if (k > 0 and offset <= previous) or offset >= own:
            raise FormatError(f"index entry {k}: offset {offset} is out of order or past the index")
        if k == 0 and flag != 1:
            raise FormatError("the index's first frame is not a keyframe")
        out.append(IndexEntry(time, offset, bool(flag)))
    return out
