"""The decoders on bytes made here, no server: C4GS, C4GV's pieces, server-sent events, PNG,
the error table and the option types."""

from __future__ import annotations

import io
import math
import struct

import httpx
import numpy as np
import pytest

import c4g_client as c4g
from c4g_client import _c4gs, _c4gv, _errors, _http, _libm, _png
from c4g_client._sse import SseDecoder, SseEvent


def c4gs_bytes(frames, precision="f32", feature_width=None):
    """A C4GS payload written from the spec (formats/src/c4gs.rs), independently of
    the reader under test: version 1, or with ``feature_width`` version 2, whose frames hold a
    sixth column (the features) after the five."""
    code, dtype = {"f32": (0, "<f4"), "f16": (1, "<f2")}[precision]
    n = len(frames[0][1][3]) if frames else 0
    version = 1 if feature_width is None else 2
    out = b"C4GS" + struct.pack("<HBBII", version, code, 0, len(frames), n)
    if feature_width is not None:
        out += struct.pack("<I", feature_width)
    for time, columns in frames:
        out += struct.pack("<d", time)
        for column in columns:
            out += np.asarray(column, dtype=np.float32).astype(dtype).tobytes()
    return out


def one_gaussian(x=1.0):
    return [
        [x, -2.0, 3.5],
        [0.1, 0.2, 0.3],
        [1.0, 0.0, 0.0, 0.0],
        [0.75],
        [0.25, 0.5, 1.0],
    ]


def test_c4gs_f32_reads_the_documented_layout_exactly():
    payload = c4gs_bytes([(0.5, one_gaussian()), (1.0, one_gaussian(4.0))])
    first, second = _c4gs.decode(payload)
    assert first.time == 0.5 and second.time == 1.0
    np.testing.assert_array_equal(first.means, np.float32([[1.0, -2.0, 3.5]]))
    np.testing.assert_array_equal(first.scales, np.float32([[0.1, 0.2, 0.3]]))
    np.testing.assert_array_equal(first.quats, np.float32([[1, 0, 0, 0]]))
    np.testing.assert_array_equal(first.opacities, np.float32([0.75]))
    np.testing.assert_array_equal(first.colors, np.float32([[0.25, 0.5, 1.0]]))
    assert second.means[0, 0] == 4.0
    assert first.means.dtype == np.float32


def test_c4gs_f16_widens_each_half_exactly():
    columns = one_gaussian(1e-3)
    (s,) = _c4gs.decode(c4gs_bytes([(0.0, columns)], "f16"))
    expected = np.float32(np.float16(np.float32(1e-3)))
    assert s.means[0, 0] == expected
    assert s.scales.dtype == np.float32
    # 0.1 is not a half: it comes back as the half nearest to it.
    assert s.scales[0, 0] == np.float32(np.float16(0.1))


def test_c4gs_refuses_short_payloads_other_versions_and_magic():
    payload = c4gs_bytes([(0.5, one_gaussian())])
    with pytest.raises(c4g.FormatError, match="needs"):
        _c4gs.decode(payload[:-1])
    with pytest.raises(c4g.FormatError, match="16-byte header"):
        _c4gs.decode(payload[:10])
    with pytest.raises(c4g.FormatError, match="version 3; this reader reads versions 1 and 2"):
        _c4gs.decode(payload[:4] + b"\x03" + payload[5:])
    with pytest.raises(c4g.FormatError, match="not a C4GS"):
        _c4gs.decode(b"XXXX" + payload[4:])
    # The reserved byte is ignored, as the spec says.
    assert len(_c4gs.decode(payload[:7] + b"\x09" + payload[8:])) == 1


def test_c4gs_of_no_frames_is_an_empty_list():
    assert _c4gs.decode(b"C4GS" + struct.pack("<HBBII", 1, 0, 0, 0, 512)) == []


def with_features(columns, features):
    """One frame's columns followed by its feature rows: version 2's layout."""
    return columns + [features]


FEATURES = [[0.5, -1.25, 3.0], [1e-3, 0.0, -7.5]]


def test_c4gs_version_1_sets_have_no_features():
    (s,) = _c4gs.decode(c4gs_bytes([(0.5, one_gaussian())]))
    assert s.features is None and s.feature_width == 0 and "features" not in s.arrays()


@pytest.mark.parametrize("precision", ["f32", "f16"])
def test_c4gs_version_2_reads_the_features_after_the_colours(precision):
    two = [np.concatenate([np.ravel(a), np.ravel(b)]) for a, b in zip(one_gaussian(), one_gaussian(4.0))]
    frames = [(0.25, with_features(two, FEATURES)), (0.5, with_features(two, FEATURES[::-1]))]
    payload = c4gs_bytes(frames, precision, feature_width=3)
    first, second = _c4gs.decode(payload)
    wire = np.float32 if precision == "f32" else np.float16
    np.testing.assert_array_equal(first.features, np.float32(FEATURES).astype(wire).astype(np.float32))
    np.testing.assert_array_equal(second.features, first.features[::-1])
    assert first.features.dtype == np.float32 and first.feature_width == 3
    # The five columns read as in version 1.
    np.testing.assert_array_equal(first.means, np.float32([[1.0, -2.0, 3.5], [4.0, -2.0, 3.5]]))
    np.testing.assert_array_equal(first.colors[1], np.float32([0.25, 0.5, 1.0]).astype(wire))
    assert (first.time, second.time) == (0.25, 0.5)


def test_c4gs_version_2_refuses_short_and_hostile_payloads():
    payload = c4gs_bytes([(0.5, with_features(one_gaussian(), [[1.0, 2.0]]))], feature_width=2)
    assert _c4gs.decode(payload)[0].features.tolist() == [[1.0, 2.0]]
    with pytest.raises(c4g.FormatError, match="with 2 feature channels needs"):
        _c4gs.decode(payload[:-1])
    with pytest.raises(c4g.FormatError, match="needs"):
        _c4gs.decode(payload + b"\x00")
    with pytest.raises(c4g.FormatError, match="feature width after the header"):
        _c4gs.decode(payload[:18])
    with pytest.raises(c4g.FormatError, match="at least 1; got 0"):
        _c4gs.decode(payload[:16] + struct.pack("<I", 0) + payload[20:])
    # Headers that claim terabytes are refused by the payload's length, before any allocation.
    huge_width = payload[:16] + struct.pack("<I", 2**32 - 1) + payload[20:]
    with pytest.raises(c4g.FormatError, match="needs"):
        _c4gs.decode(huge_width)
    huge_count = b"C4GS" + struct.pack("<HBBIII", 2, 0, 0, 2**32 - 1, 2**32 - 1, 2**32 - 1)
    with pytest.raises(c4g.FormatError, match="needs"):
        _c4gs.decode(huge_count)
    # A version 1 reading of a version 2 payload is what the version field prevents: the width
    # field shifts every column, so the same bytes as version 1 do not add up.
    with pytest.raises(c4g.FormatError, match="needs"):
        _c4gs.decode(payload[:4] + b"\x01" + payload[5:])


def test_packed_feature_columns_are_checked_like_the_others():
    columns = [np.float32(c).tobytes() for c in one_gaussian()]
    s = _c4gs.unpack_columns(0.1, 1, "f32", columns, np.float32([[1, 2, 3, 4]]).tobytes(), 4)
    assert s.features.shape == (1, 4)
    with pytest.raises(c4g.FormatError, match="width 4 need 16 bytes; got 12"):
        _c4gs.unpack_columns(0.1, 1, "f32", columns, np.float32([1, 2, 3]).tobytes(), 4)
    with pytest.raises(c4g.FormatError, match="feature width of 0"):
        _c4gs.unpack_columns(0.1, 1, "f32", columns, b"\x00" * 4, 0)
    # gRPC's message without features: width 0 and empty bytes.
    assert _c4gs.unpack_columns(0.1, 1, "f32", columns, b"", 0).features is None


def feature_set(n=4, width=3, time=0.0):
    rng = np.random.default_rng(n)
    return c4g.GaussianSet(
        time,
        rng.normal(size=(n, 3)).astype(np.float32),
        np.tile(np.float32([1, 0, 0, 0]), (n, 1)),
        np.full((n, 3), 0.1, np.float32),
        np.full(n, 0.5, np.float32),
        np.full((n, 3), 0.25, np.float32),
        np.arange(n * width, dtype=np.float32).reshape(n, width),
    )


def test_a_sets_features_travel_with_it_and_are_shape_checked():
    s = feature_set()
    assert s.feature_width == 3 and "features of 3" in repr(s)
    picked = s.take(np.array([True, False, True, False]))
    np.testing.assert_array_equal(picked.features, s.features[[0, 2]])
    np.testing.assert_array_equal(s.take(slice(1, 3)).features, s.features[1:3])
    np.testing.assert_array_equal(s.arrays()["features"], s.features)
    stacked = c4g.stack([s, feature_set(time=0.5)])
    assert stacked["features"].shape == (2, 4, 3)
    with pytest.raises(ValueError, match="1 of 2 sets have features"):
        c4g.stack([s, _without_features(s)])
    with pytest.raises(ValueError, match=r"features has shape \(3, 3\); expected \(4, F\)"):
        c4g.GaussianSet(s.time, s.means, s.quats, s.scales, s.opacities, s.colors, s.features[:3])
    with pytest.raises(ValueError, match="features has shape"):
        c4g.GaussianSet(s.time, s.means, s.quats, s.scales, s.opacities, s.colors, s.features.ravel())


def _without_features(s):
    return c4g.GaussianSet(s.time, s.means, s.quats, s.scales, s.opacities, s.colors)


def test_json_frames_with_features_read_as_rows():
    frame = {"t": 0.5, "count": 1, "means": [[1, 2, 3]], "scales": [[0.1, 0.1, 0.1]],
             "rotations": [[1, 0, 0, 0]], "opacities": [0.5], "colors": [[0.2, 0.3, 0.4]],
             "features": [[0.1, -0.2]]}  # fmt: skip
    (s,) = c4g._sets.from_json({"frames": [frame]})
    np.testing.assert_array_equal(s.features, np.float32([[0.1, -0.2]]))
    empty = {**frame, "count": 0, "means": [], "scales": [], "rotations": [], "opacities": [],
             "colors": [], "features": []}  # fmt: skip
    (none,) = c4g._sets.from_json({"frames": [empty]})
    assert len(none) == 0 and none.features.shape[0] == 0


def test_a_segments_masks_decode_their_runs_and_refuse_runs_that_do_not_cover_the_image():
    body = {"width": 4, "height": 2, "t": 0.2, "threshold": 0.8, "feature": [1.0, 0.0],
            "gaussians": [3, 17], "masks": [{"t": 0.0, "area": 3, "counts": [0, 2, 5, 1]}]}  # fmt: skip
    segment = c4g.Segment.from_json(body)
    (mask,) = segment.masks
    assert mask.array.tolist() == [[True, True, False, False], [False, False, False, True]]
    assert mask.array.sum() == mask.area and segment.gaussians.tolist() == [3, 17]
    assert segment.feature.dtype == np.float32 and segment.t == 0.2
    short = {**body, "masks": [{"t": 0.0, "area": 3, "counts": [0, 2, 5]}]}
    with pytest.raises(c4g.FormatError, match="sum to the 4x2 pixels; got 7"):
        c4g.Segment.from_json(short)
    with pytest.raises(c4g.FormatError, match="not a segment"):
        c4g.Segment.from_json({"width": 4})


def test_a_features_render_is_read_by_its_channels_header():
    from c4g_client import _endpoints

    call = _endpoints.render("clip", 0.1, format="features")
    assert call.json["format"] == "features"
    values = np.arange(2 * 3 * 5, dtype="<f4")
    headers = {"x-c4g-width": "3", "x-c4g-height": "2", "x-c4g-channels": "5", "x-c4g-time": "0.1"}
    image = call.parse(httpx.Response(200, content=values.tobytes(), headers=headers))
    assert isinstance(image, c4g.FeatureImage) and image.array.shape == (2, 3, 5) and image.channels == 5
    np.testing.assert_array_equal(image.array[1, 2], values[25:30])
    assert image.time == 0.1 and image.to_uint8().shape == (2, 3, 3)
    with pytest.raises(c4g.FormatError, match="X-C4G-Channels"):
        call.parse(httpx.Response(200, content=values.tobytes(), headers={**headers, "x-c4g-channels": ""}))
    with pytest.raises(c4g.FormatError, match="is 120 bytes; got 116"):
        call.parse(httpx.Response(200, content=values.tobytes()[:-4], headers=headers))
    with pytest.raises(ValueError, match="unknown render format"):
        _endpoints.render("clip", 0.1, format="feature")


def leb128(u: int) -> bytes:
    out = bytearray()
    while u >= 0x80:
        out.append((u & 0x7F) | 0x80)
        u >>= 7
    out.append(u)
    return bytes(out)


def zigzag(v: int) -> int:
    return 2 * v if v >= 0 else -2 * v - 1


def test_c4gv_varints_read_zigzag_leb128_of_up_to_five_bytes():
    values = [0, -1, 1, 63, -64, 64, 2**30 - 1, -(2**30), 2**34 - 1, -(2**34)]
    body = b"".join(leb128(zigzag(v)) for v in values)
    assert _c4gv._varints(body, len(values), "t").tolist() == values
    with pytest.raises(c4g.FormatError, match="cut short"):
        _c4gv._varints(body[:-1], len(values), "t")
    with pytest.raises(c4g.FormatError, match="after the last value"):
        _c4gv._varints(body + b"\x00", len(values), "t")
    with pytest.raises(c4g.FormatError, match="too long"):
        _c4gv._varints(b"\x80\x80\x80\x80\x80\x00", 1, "t")


def c4gv_stream(
    cells_per_frame, steps=(1e-3, 1 / 1024, 1 / 4096, 1 / 1023, 1 / 1023), deflate=False, static=None
):
    """A C4GV stream written from the spec (formats/src/c4gv/mod.rs): the Gaussians marked
    in ``static`` once, in the static record (with their first frame's cells), the others in a
    keyframe then delta frames: the reader's input, built independently of it."""
    import zlib

    n = len(cells_per_frame[0])
    static = static or [False] * n
    mask = bytearray((n + 7) // 8)
    for i, s in enumerate(static):
        if s:
            mask[i // 8] |= 1 << (i % 8)
    out = bytearray(b"C4GV" + struct.pack("<HBBII", 1, 0, 0, n, sum(static)) + struct.pack("<5d", *steps))
    out += mask

    def body(rows):
        raw = b"".join(leb128(zigzag(int(rows[g][k]))) for k in range(14) for g in range(len(rows)))
        if deflate:
            packer = zlib.compressobj(9, zlib.DEFLATED, -15)
            stored = packer.compress(raw) + packer.flush()
            if len(stored) < len(raw):
                return 1, struct.pack("<I", len(raw)) + stored
        return 0, struct.pack("<I", len(raw)) + raw

    coding, payload = body([c for c, s in zip(cells_per_frame[0], static) if s])
    out += struct.pack("<BBI", 1, coding, len(payload)) + payload
    index = []
    previous = None
    for f, all_cells in enumerate(cells_per_frame):
        cells = [c for c, s in zip(all_cells, static) if not s]
        rows = cells if previous is None else [[a - b for a, b in zip(r, p)] for r, p in zip(cells, previous)]
        kind = 2 if previous is None else 3
        coding, payload = body(rows)
        head = struct.pack("<d", 0.1 * f)
        index.append((0.1 * f, len(out), kind == 2))
        out += struct.pack("<BBI", kind, coding, len(head) + len(payload)) + head + payload
        previous = cells
    entries = b"".join(struct.pack("<dQB", t, o, k) for t, o, k in index)
    payload = entries + struct.pack("<Q", len(out)) + b"C4GI"
    out += struct.pack("<BBI", 4, 0, len(payload)) + payload
    return bytes(out)


def cells(x, log_scale, opacity=512, w=4096):
    return [x, -x, 7, log_scale, log_scale, log_scale, w, 0, 0, 0, opacity, 100, 200, 300]


@pytest.mark.parametrize("deflate", [False, True])
def test_c4gv_decodes_cells_as_the_spec_tables_say(deflate):
    frames = [
        [cells(10, -2048), cells(-5, 0)],
        [cells(11, -2047), cells(-5, 1)],
        [cells(13, -2047), cells(-6, 1)],
    ]
    stream = c4gv_stream(frames, deflate=deflate)
    sets = c4g.decode_c4gv(stream)
    assert [s.time for s in sets] == [0.0, 0.1, 0.2]
    last = sets[2]
    np.testing.assert_array_equal(last.means[0], np.float32([13 * 1e-3, -13 * 1e-3, 7 * 1e-3]))
    assert last.scales[0, 0] == np.float32(np.exp(-2047 / 1024))
    assert last.scales[1, 0] == np.float32(np.exp(1 / 1024))
    np.testing.assert_array_equal(last.quats[0], np.float32([1, 0, 0, 0]))
    assert last.opacities[0] == np.float32(512 / 1023)
    np.testing.assert_array_equal(last.colors[1], np.float32([100 / 1023, 200 / 1023, 300 / 1023]))


def test_c4gv_scales_are_the_c_librarys_exp_without_a_call_a_value(monkeypatch):
    """Bit for bit what the Rust decoder's ``f64::exp`` (the C library's) gives, but vectorised:
    the reader calls :func:`math.exp` only where NumPy's last bit could change the float32."""
    rng = np.random.default_rng(7)
    n = 2000
    log_scales = rng.integers(-20000, 9000, size=(n, 3))
    rows = [[g, -g, 7, *map(int, log_scales[g]), 4096, 0, 0, 0, 512, 100, 200, 300] for g in range(n)]
    stream = c4gv_stream([rows], deflate=True)
    calls = []
    exp = math.exp
    monkeypatch.setattr(math, "exp", lambda v: calls.append(v) or exp(v))
    (s,) = c4g.decode_c4gv(stream)
    monkeypatch.undo()
    expected = np.float32([[math.exp(v / 1024) for v in row] for row in log_scales.tolist()])
    assert s.scales.tobytes() == expected.tobytes()
    assert len(calls) < n * 3 // 100, f"{len(calls)} calls to math.exp for {n * 3} scales"


def test_the_c_librarys_exp_and_log_over_arrays_bit_for_bit():
    # Every log-scale cell of the default step (1/1024) from a scale of 1e-30 to 1e30.
    cells = np.arange(-70700, 70700) / 1024
    assert _libm.exp_f32(cells).tobytes() == np.float32([math.exp(v) for v in cells.tolist()]).tobytes()
    scales = np.exp(cells)
    assert _libm.log_f32(scales).tobytes() == np.float32([math.log(v) for v in scales.tolist()]).tobytes()
    # Values whose result lands next to a point halfway between two float32s, where NumPy's last
    # bit could round the other way: the exact path takes them.
    rng = np.random.default_rng(3)

    def halfway(values: np.ndarray) -> list:
        below = values.astype(np.float32)
        return ((below.astype(np.float64) + np.nextafter(below, np.float32(np.inf))) / 2).tolist()

    at_exp = np.array([math.log(v) for v in halfway(np.exp(rng.uniform(-69, 69, 5000)))])
    assert _libm.exp_f32(at_exp).tobytes() == np.float32([math.exp(v) for v in at_exp.tolist()]).tobytes()
    at_log = np.array([math.exp(v) for v in halfway(rng.uniform(-69, 69, 5000))])
    assert _libm.log_f32(at_log).tobytes() == np.float32([math.log(v) for v in at_log.tolist()]).tobytes()
    # The extremes.
    with np.errstate(divide="ignore"):
        extremes = [-np.inf, np.inf, np.nan, 1000.0, -1000.0, 0.0]
        np.testing.assert_array_equal(
            _libm.exp_f32(np.array(extremes)), np.float32([0, np.inf, np.nan, np.inf, 0, 1])
        )
        np.testing.assert_array_equal(
            _libm.log_f32(np.array([0.0, np.inf, np.nan, 1.0])), np.float32([-np.inf, np.inf, np.nan, 0])
        )


def test_c4gv_holds_static_gaussians_in_every_frame():
    still = cells(3, -100, 700)
    frames = [[cells(k, -k), still, cells(-k, k), still] for k in range(4)]
    sets = c4g.decode_c4gv(c4gv_stream(frames, static=[False, True, False, True], deflate=True))
    moving = c4g.decode_c4gv(c4gv_stream(frames))
    for s, m in zip(sets, moving):
        for name in ("means", "quats", "scales", "opacities", "colors"):
            np.testing.assert_array_equal(getattr(s, name), getattr(m, name))
    assert sets[3].means[1, 0] == sets[0].means[1, 0] == np.float32(3e-3)


def test_c4gv_decodes_the_same_whatever_the_chunking():
    frames = [[cells(k + g, -k, 500 + g) for g in range(9)] for k in range(5)]
    stream = c4gv_stream(frames, deflate=True)
    whole = c4g.decode_c4gv(stream)
    for size in (1, 7, 64):
        decoder = c4g.C4GVDecoder()
        got = []
        for at in range(0, len(stream), size):
            decoder.feed(stream[at : at + size])
            got.extend(decoder.frames())
        decoder.finish()
        assert len(got) == len(whole)
        for a, b in zip(got, whole):
            for name in ("means", "quats", "scales", "opacities", "colors"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert decoder.done and [e.keyframe for e in decoder.index] == [True, False, False, False, False]


def test_c4gv_refuses_what_the_spec_forbids():
    stream = c4gv_stream([[cells(1, 0)], [cells(2, 0)]])
    with pytest.raises(c4g.StreamInterrupted, match="before its index"):
        c4g.decode_c4gv(stream[:-5])
    with pytest.raises(c4g.FormatError, match="after the index"):
        c4g.decode_c4gv(stream + b"\x00")
    with pytest.raises(c4g.FormatError, match="not a C4GV"):
        c4g.decode_c4gv(b"C4GX" + stream[4:])
    with pytest.raises(c4g.FormatError, match="version"):
        c4g.decode_c4gv(stream[:4] + b"\x02" + stream[5:])
    zero_rotation = c4gv_stream([[cells(1, 0, w=0)]])
    with pytest.raises(c4g.FormatError, match="rotation"):
        c4g.decode_c4gv(zero_rotation)
    too_opaque = c4gv_stream([[cells(1, 0, opacity=2000)]])
    with pytest.raises(c4g.FormatError, match="opacity"):
        c4g.decode_c4gv(too_opaque)
    # A log-scale cell whose exp overflows is an infinite scale, not Python's OverflowError.
    too_large = c4gv_stream([[cells(1, 800 * 1024)]])
    with pytest.raises(c4g.FormatError, match="a scale is not finite"):
        c4g.decode_c4gv(too_large)


def test_sse_events_survive_any_chunking():
    text = (
        '\ufeff: keep-alive\r\nevent: job\r\ndata: {"a":\r\ndata: 1}\r\n\r\n'
        "event: job\rdata: two\r\rdata: plain\n\n"
    ).encode()
    expected = [SseEvent("job", '{"a":\n1}'), SseEvent("job", "two"), SseEvent("message", "plain")]
    for size in range(1, len(text) + 1):
        decoder = SseDecoder()
        events = []
        for at in range(0, len(text), size):
            events.extend(decoder.push(text[at : at + size]))
        assert events == expected, size


def test_png_round_trips_and_the_pure_reader_matches_pillow():
    rng = np.random.default_rng(0)
    pixels = rng.integers(0, 256, size=(13, 17, 3), dtype=np.uint8)
    assert (_png.decode(_png.encode(pixels), pure=True) == pixels).all()
    Image = pytest.importorskip("PIL.Image")
    # Pillow's encoder picks a filter per row (Sub, Up, Average, Paeth): all of them are read.
    smooth = (np.add.outer(np.arange(40), np.arange(50))[:, :, None] * [1, 2, 3] % 256).astype(np.uint8)
    for a in (pixels, smooth, smooth[:, :, :1].copy()):
        buffer = io.BytesIO()
        Image.fromarray(a.squeeze()).save(buffer, format="PNG", optimize=True)
        pure = _png.decode(buffer.getvalue(), pure=True)
        assert (pure == _png.decode(buffer.getvalue())).all()
        assert (pure.reshape(a.shape) == a).all()


def test_every_kind_of_the_error_table_has_its_class_status_and_grpc_code():
    table = {
        "invalid_input": (400, "INVALID_ARGUMENT", c4g.InvalidInput),
        "unauthorized": (401, "UNAUTHENTICATED", c4g.Unauthorized),
        "not_found": (404, "NOT_FOUND", c4g.NotFound),
        "too_large": (413, "RESOURCE_EXHAUSTED", c4g.TooLarge),
        "unsupported_media": (415, "INVALID_ARGUMENT", c4g.UnsupportedMedia),
        "unreadable_media": (422, "INVALID_ARGUMENT", c4g.UnreadableMedia),
        "unsupported": (422, "INVALID_ARGUMENT", c4g.Unsupported),
        "timed_out": (408, "DEADLINE_EXCEEDED", c4g.TimedOut),
        "busy": (429, "RESOURCE_EXHAUSTED", c4g.Busy),
        "not_ready": (503, "UNAVAILABLE", c4g.NotReady),
        "draining": (503, "UNAVAILABLE", c4g.Draining),
        "overloaded": (503, "UNAVAILABLE", c4g.Overloaded),
        "unavailable": (503, "UNAVAILABLE", c4g.Unavailable),
        "insufficient_storage": (507, "RESOURCE_EXHAUSTED", c4g.InsufficientStorage),
        "internal": (500, "INTERNAL", c4g.InternalError),
    }
    assert set(_errors.KINDS) == set(table)
    for kind, (status, code, cls) in table.items():
        assert _errors.KINDS[kind] == (cls, status, code)
        response = httpx.Response(status, json={"error": "why", "kind": kind}, headers={"retry-after": "3"})
        error = _http.error_from(response)
        assert type(error) is cls and (error.status, error.kind, error.message) == (status, kind, "why")
        assert error.retry_after == 3.0 and isinstance(error, c4g.ApiError)
        via_grpc = _errors.grpc_api_error(code, "why", kind)
        assert type(via_grpc) is cls and via_grpc.status == status and via_grpc.grpc_code == code
    assert issubclass(c4g.Busy, c4g.RetryableError) and not issubclass(c4g.NotFound, c4g.RetryableError)


def test_an_answer_that_is_not_the_apis_json_still_raises_with_its_status():
    error = _http.error_from(httpx.Response(502, text="<html>bad gateway</html>"))
    assert type(error) is c4g.ApiError and error.kind == "http_502" and "bad gateway" in error.message
    error = _http.error_from(httpx.Response(404, text=""))
    assert isinstance(error, c4g.NotFound) and error.message == "Not Found"
    # A gRPC status refused before the service (no c4g-error-kind) reads by its code.
    assert isinstance(_errors.grpc_api_error("INVALID_ARGUMENT", "bad bytes", None), c4g.InvalidInput)
    # A kind this version does not know is still readable.
    error = _errors.api_error(418, "teapot", "short and stout")
    assert type(error) is c4g.ApiError and error.kind == "teapot"


def test_options_serialise_to_the_apis_json():
    assert c4g.Keyframes.every(0.5).to_json() == {"every_s": 0.5}
    assert c4g.Keyframes.count(8).to_json() == {"count": 8}
    assert c4g.Keyframes.adaptive(0.005, max=32).to_json() == {"tolerance": 0.005, "max": 32}
    assert c4g.Prune(contribution_px=0.5).to_json() == {"contribution_px": 0.5}
    assert c4g.Prune(drop_queries=True).to_json() == {"drop_queries": True}
    assert c4g.Orbit(2.0, 30).to_json() == {"kind": "orbit", "depth": 2.0, "angle_degrees": 30}
    camera = c4g.Camera(np.eye(4), c4g.Intrinsics(fx=1.0, fy=1.0))
    assert camera.to_json()["world_to_camera"] == [float(v) for v in np.eye(4).reshape(-1)]
    assert camera.to_json()["intrinsics"] == {"fx": 1.0, "fy": 1.0, "cx": 0.5, "cy": 0.5}
    np.testing.assert_array_equal(
        c4g.Intrinsics().matrix(100, 50), [[87.67, 0, 50], [0, 43.835, 25], [0, 0, 1]]
    )


def test_base_urls_are_normalised_and_segments_encoded():
    assert _http.normalise_base_url("127.0.0.1:9000") == "http://127.0.0.1:9000"
    assert (
        _http.url_for("http://h:1/prefix", ["v1", "clips", "a b/c"]) == "http://h:1/prefix/v1/clips/a%20b%2Fc"
    )
    with pytest.raises(ValueError):
        _http.normalise_base_url("ftp://h")
