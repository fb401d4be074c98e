//! The codec's unit tests: round trips within the bounds, streaming, seeking, and hostile bytes.

use c4g_scene::GaussianSet;

use super::decoder::read_varint;
use super::*;
use c4g_scene::test_rng::{Rng, unit};
use proptest::prelude::*;

/// A clip of `frames` sets of `n` Gaussians: the first `still` never change, the others
/// move smoothly in every attribute.
fn clip(n: usize, still: usize, frames: usize, seed: u64) -> Vec<(f64, GaussianSet)> {
    let mut rng = Rng(seed);
    let base: Vec<[f32; 16]> = (0..n)
        .map(|_| std::array::from_fn(|_| rng.range(0.0, 1.0)))
        .collect();
    (0..frames)
        .map(|f| {
            let t = f as f64 / 30.0;
            let mut columns = (vec![], vec![], vec![], vec![], vec![]);
            for (i, b) in base.iter().enumerate() {
                let m = if i < still { 0.0 } else { 1.0 };
                let w = |k: usize| (f64::from(b[k]) * 6.0 + t * (1.0 + f64::from(b[15]))).sin();
                let p = |k: usize| (f64::from(b[k]) * 6.0 - 3.0 + m * 0.3 * w(k)) as f32;
                columns.0.push([p(0), p(1), p(2) + 4.0]);
                let s = |k: usize| (0.01 + 0.2 * f64::from(b[k]) * (1.0 + m * 0.2 * w(k))) as f32;
                columns.1.push([s(3), s(4), s(5)]);
                let q = |k: usize| f64::from(b[k]) - 0.5 + m * 0.1 * w(k);
                columns.2.push(unit([q(6), q(7), q(8), q(9)]));
                columns
                    .3
                    .push((f64::from(b[10]) * (1.0 - m * 0.1 * (1.0 + w(10)) / 2.0)) as f32);
                let c = |k: usize| (f64::from(b[k]) * (1.0 - m * 0.05 * (1.0 + w(k)))) as f32;
                columns.4.push([c(11), c(12), c(13)]);
            }
            let set =
                GaussianSet::new(columns.0, columns.1, columns.2, columns.3, columns.4).unwrap();
            set.validate().unwrap();
            (t, set)
        })
        .collect()
}

fn refs(frames: &[(f64, GaussianSet)]) -> impl Iterator<Item = (f64, &GaussianSet)> {
    frames.iter().map(|(t, s)| (*t, s))
}

fn options(position_error: f64) -> EncodeOptions {
    EncodeOptions {
        position_error,
        ..EncodeOptions::default()
    }
}

/// The largest error of each channel group of `decoded` against `original`, in f64:
/// position (scene units), scale (relative, or absolute below the floor), rotation
/// (radians), opacity, colour.
fn errors(original: &GaussianSet, decoded: &GaussianSet) -> [f64; 5] {
    assert_eq!(original.len(), decoded.len());
    let mut worst = [0.0f64; 5];
    let diff = |a: f32, b: f32| (f64::from(a) - f64::from(b)).abs();
    for i in 0..original.len() {
        for k in 0..3 {
            worst[0] = worst[0].max(diff(original.positions()[i][k], decoded.positions()[i][k]));
            worst[1] = worst[1].max(scale_error(original.scales()[i][k], decoded.scales()[i][k]));
            worst[4] = worst[4].max(diff(original.colors()[i][k], decoded.colors()[i][k]));
        }
        worst[2] = worst[2].max(rotation_angle(
            original.rotations()[i],
            decoded.rotations()[i],
        ));
        worst[3] = worst[3].max(diff(original.opacities()[i], decoded.opacities()[i]));
    }
    worst
}

fn assert_within_bounds(original: &GaussianSet, decoded: &GaussianSet, position_error: f64) {
    let [p, s, r, o, c] = errors(original, decoded);
    assert!(p <= position_error, "position error {p} > {position_error}");
    assert!(s <= SCALE_ERROR, "scale error {s}");
    assert!(r <= ROTATION_ERROR, "rotation error {r}");
    assert!(o <= OPACITY_ERROR, "opacity error {o}");
    assert!(c <= COLOR_ERROR, "colour error {c}");
    decoded.validate().unwrap();
}

fn reason(err: SceneError) -> String {
    match err {
        SceneError::Format { format, reason } => {
            assert_eq!(format, "c4gv");
            reason
        }
        other => panic!("expected a C4GV format error, got {other:?}"),
    }
}

fn set_of(positions: Vec<[f32; 3]>) -> GaussianSet {
    let n = positions.len();
    GaussianSet::new(
        positions,
        vec![[0.1; 3]; n],
        vec![[1.0, 0.0, 0.0, 0.0]; n],
        vec![0.5; n],
        vec![[0.25; 3]; n],
    )
    .unwrap()
}

#[test]
fn binary_layout_is_as_documented() {
    let set = set_of(vec![[0.5, -1.0, 2.0]]);
    let opts = EncodeOptions {
        deflate: false,
        ..options(1e-3)
    };
    let bytes = encode([(0.25, &set)], &opts).unwrap();
    assert_eq!(&bytes[..4], b"C4GV");
    assert_eq!(u16::from_le_bytes([bytes[4], bytes[5]]), 1);
    assert_eq!((bytes[6], bytes[7]), (0, 0), "predictor 0, reserved 0");
    assert_eq!(read_u32(&bytes[8..]), 1, "N");
    assert_eq!(
        read_u32(&bytes[12..]),
        1,
        "one frame: every Gaussian is static"
    );
    assert_eq!(read_f64(&bytes[16..]), 1.875e-3);
    assert_eq!(read_f64(&bytes[24..]), 1.0 / 1024.0);
    assert_eq!(read_f64(&bytes[32..]), 1.0 / 4096.0);
    assert_eq!(read_f64(&bytes[40..]), 1.0 / 1023.0);
    assert_eq!(read_f64(&bytes[48..]), 1.0 / 1023.0);
    assert_eq!(bytes[56], 1, "the static mask");
    // The static record: kind, coding, length, inflated length, 14 varints.
    let st = 57;
    assert_eq!((bytes[st], bytes[st + 1]), (KIND_STATIC, CODING_STORED));
    let body_len = read_u32(&bytes[st + 6..]) as usize;
    assert_eq!(read_u32(&bytes[st + 2..]) as usize, 4 + body_len);
    let body = &bytes[st + 10..st + 10 + body_len];
    let mut values = vec![];
    let mut at = 0;
    while at < body.len() {
        let (v, used) = read_varint(&body[at..]).unwrap();
        values.push(unzigzag(v));
        at += used;
    }
    let ln = |s: f64| (s.ln() * 1024.0).round() as i64;
    assert_eq!(
        values,
        [
            267,
            -533,
            1067, // 0.5 / 1.875e-3 and so on
            ln(0.1f32 as f64),
            ln(0.1f32 as f64),
            ln(0.1f32 as f64),
            4096,
            0,
            0,
            0,
            512, // round(0.5 · 1023)
            256,
            256,
            256, // round(0.25 · 1023)
        ]
    );
    // The keyframe: no moving Gaussian, so an empty body.
    let kf = st + 10 + body_len;
    assert_eq!(
        &bytes[kf..kf + 6],
        &[KIND_KEYFRAME, CODING_STORED, 12, 0, 0, 0]
    );
    assert_eq!(read_f64(&bytes[kf + 6..]), 0.25);
    assert_eq!(read_u32(&bytes[kf + 14..]), 0);
    // The index: one entry, its own offset, the magic.
    let ix = kf + 18;
    assert_eq!(
        &bytes[ix..ix + 6],
        &[KIND_INDEX, CODING_STORED, 29, 0, 0, 0]
    );
    assert_eq!(read_f64(&bytes[ix + 6..]), 0.25);
    assert_eq!(read_u64(&bytes[ix + 14..]), kf as u64);
    assert_eq!(bytes[ix + 22], 1);
    assert_eq!(read_u64(&bytes[ix + 23..]), ix as u64);
    assert_eq!(&bytes[ix + 31..], b"C4GI");
    assert_eq!(read_index(&bytes).unwrap()[0].offset, kf as u64);
}

#[test]
fn round_trip_meets_every_stated_bound() {
    let frames = clip(64, 16, 40, 7);
    for e in [1e-2, 1e-3, 1e-4, 1e-5] {
        let bytes = encode(refs(&frames), &options(e)).unwrap();
        let back = decode(&bytes).unwrap();
        assert_eq!(back.len(), frames.len());
        for ((t, set), (tb, decoded)) in frames.iter().zip(&back) {
            assert_eq!(t, tb);
            assert_within_bounds(set, decoded, e);
        }
    }
}

#[test]
fn the_bounds_hold_at_the_edges_of_every_range() {
    let e = 1e-3;
    let edge = (POSITION_RANGE * e) as f32;
    let set = GaussianSet::new(
        vec![
            [edge, -edge, 0.0],
            [999.9991, -0.000_937_4, 1e-30],
            [0.0; 3],
        ],
        vec![
            [0.0, SCALE_FLOOR / 3.0, f32::MAX],
            [f32::MIN_POSITIVE, 1e-10, 1e30],
            [1.0; 3],
        ],
        vec![
            [1.0009, 0.0, 0.0, 0.0],
            unit([0.5, -0.5, 0.5, -0.5]),
            unit([1e-6, 0.7, -0.7, 1e-3]),
        ],
        vec![0.0, 1.0, 0.5 / 1023.0],
        vec![
            [0.0, COLOR_MAX, 1.0],
            [15.999, 1.0 / 2046.0, 0.999],
            [0.0; 3],
        ],
    )
    .unwrap();
    set.validate().unwrap();
    let bytes = encode([(0.0, &set), (1.0, &set)], &options(e)).unwrap();
    for (_, decoded) in decode(&bytes).unwrap() {
        assert_within_bounds(&set, &decoded, e);
        assert!(decoded.scales()[0][0] > 0.0 && decoded.scales()[0][0] < 6e-20);
    }
}

#[test]
fn values_outside_the_grid_or_the_layout_are_refused_by_the_encoder() {
    let e = 1e-3;
    let beyond = (POSITION_RANGE * e * 1.001) as f32;
    let (mut encoder, _) = Encoder::new(2, &options(e)).unwrap();
    let cases: Vec<(GaussianSet, &str)> = vec![
        (
            set_of(vec![[0.0; 3], [0.0, beyond, 0.0]]),
            "beyond C4GV's range",
        ),
        (set_of(vec![[0.0; 3], [f32::NAN, 0.0, 0.0]]), "not finite"),
        (
            set_of(vec![[0.0; 3], [f32::INFINITY, 0.0, 0.0]]),
            "not finite",
        ),
        (
            GaussianSet::new(
                vec![[0.0; 3]; 2],
                vec![[0.1; 3]; 2],
                vec![[1.0, 0.0, 0.0, 0.0]; 2],
                vec![0.5; 2],
                vec![[0.0; 3], [16.5, 0.0, 0.0]],
            )
            .unwrap(),
            "beyond C4GV's range (0 to 16)",
        ),
        (
            GaussianSet::new(
                vec![[0.0; 3]; 2],
                vec![[0.1; 3], [f32::INFINITY, 0.1, 0.1]],
                vec![[1.0, 0.0, 0.0, 0.0]; 2],
                vec![0.5; 2],
                vec![[0.0; 3]; 2],
            )
            .unwrap(),
            "scale",
        ),
    ];
    for (set, expected) in cases {
        match encoder.push(0.0, &set).unwrap_err() {
            SceneError::InvalidGaussian { index, reason } => {
                assert_eq!(index, 1);
                assert!(reason.contains(expected), "{reason}");
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    // Nothing was written: the encoder still starts with a keyframe at any time.
    let ok = encoder.push(-5.0, &set_of(vec![[0.0; 3]; 2])).unwrap();
    assert_eq!(ok[0], KIND_STATIC);
}

#[test]
fn a_bound_of_zero_negative_or_not_finite_and_a_zero_keyframe_interval_are_refused() {
    for e in [0.0, -1e-3, f64::NAN, f64::INFINITY] {
        let err = Encoder::new(1, &options(e)).unwrap_err();
        assert!(reason(err).contains("finite and positive"));
        let set = set_of(vec![[0.0; 3]]);
        assert!(encode([(0.0, &set)], &options(e)).is_err());
    }
    let opts = EncodeOptions {
        keyframe_interval: 0,
        ..options(1e-3)
    };
    assert!(reason(Encoder::new(1, &opts).unwrap_err()).contains("keyframe interval"));
}

#[test]
fn frames_of_another_length_or_out_of_time_order_are_refused() {
    let (mut encoder, _) = Encoder::new(2, &options(1e-3)).unwrap();
    let two = set_of(vec![[0.0; 3]; 2]);
    let err = encoder.push(0.0, &set_of(vec![[0.0; 3]])).unwrap_err();
    assert!(reason(err).contains("frame 0 holds 1 Gaussians; the stream holds 2"));
    encoder.push(1.0, &two).unwrap();
    for t in [1.0, 0.5, f64::NAN, f64::INFINITY] {
        assert!(reason(encoder.push(t, &two).unwrap_err()).contains("time"));
    }
    encoder.push(1.5, &two).unwrap();
}

#[test]
fn the_loop_is_closed_a_frame_decodes_the_same_however_far_from_its_keyframe() {
    // 201 frames of a random walk of every attribute; frame 200 is frame 1's set again.
    let mut frames = clip(32, 0, 201, 3);
    let mut rng = Rng(11);
    for f in 2..200 {
        let (_, previous) = &frames[f - 1];
        let mut walk = |v: f32, size: f64| v + rng.range(-size, size);
        let mut p = previous.positions().to_vec();
        p.iter_mut().flatten().for_each(|v| *v = walk(*v, 0.01));
        let set = GaussianSet::new(
            p,
            frames[f].1.scales().to_vec(),
            frames[f].1.rotations().to_vec(),
            frames[f].1.opacities().to_vec(),
            frames[f].1.colors().to_vec(),
        )
        .unwrap();
        frames[f].1 = set;
    }
    frames[200].1 = frames[1].1.clone();
    let e = 1e-3;
    let opts = EncodeOptions {
        keyframe_interval: 1000,
        ..options(e)
    };
    let bytes = encode(refs(&frames), &opts).unwrap();
    let back = decode(&bytes).unwrap();
    // Frame 200 is 199 deltas from the only keyframe and decodes exactly as frame 1.
    assert_eq!(back[200].1, back[1].1);
    let (first, last) = (
        errors(&frames[1].1, &back[1].1),
        errors(&frames[200].1, &back[200].1),
    );
    assert!(
        last[0] <= first[0] && last[0] <= e,
        "{last:?} against {first:?}"
    );
    // And every frame is what coding it alone, as a keyframe, gives.
    let alone = EncodeOptions {
        keyframe_interval: 1,
        ..opts
    };
    assert_eq!(
        decode(&encode(refs(&frames), &alone).unwrap()).unwrap(),
        back
    );
}

#[test]
fn seeking_from_every_keyframe_gives_the_sets_decoding_from_the_start_gives() {
    let frames = clip(40, 10, 37, 5);
    let opts = EncodeOptions {
        keyframe_interval: 8,
        ..options(1e-3)
    };
    let bytes = encode(refs(&frames), &opts).unwrap();
    let all = decode(&bytes).unwrap();
    let index = read_index(&bytes).unwrap();
    assert_eq!(index.len(), 37);
    let keyframes: Vec<usize> = (0..37).filter(|f| index[*f].keyframe).collect();
    assert_eq!(keyframes, [0, 8, 16, 24, 32]);
    for (f, entry) in index.iter().enumerate() {
        assert_eq!(entry.time, frames[f].0);
        assert_eq!(seek(&bytes, entry.time).unwrap(), all[f..], "frame {f}");
        // Between two frames: from the earlier.
        let between = entry.time + 0.5 / 30.0;
        assert_eq!(seek(&bytes, between).unwrap(), all[f..]);
    }
    assert_eq!(seek(&bytes, -1.0).unwrap(), all);
    assert_eq!(seek(&bytes, f64::NEG_INFINITY).unwrap(), all);
    assert_eq!(seek(&bytes, f64::INFINITY).unwrap(), all[36..]);
    assert!(seek(&bytes, f64::NAN).is_err());
}

#[test]
fn seeking_reads_nothing_before_the_keyframe() {
    let frames = clip(20, 0, 20, 8);
    let opts = EncodeOptions {
        keyframe_interval: 10,
        ..options(1e-3)
    };
    let mut bytes = encode(refs(&frames), &opts).unwrap();
    let all = decode(&bytes).unwrap();
    let index = read_index(&bytes).unwrap();
    // Spoil frames 1 to 9: a seek to frame 12 never reads them.
    for b in &mut bytes[index[1].offset as usize..index[10].offset as usize] {
        *b = 0xAA;
    }
    assert_eq!(seek(&bytes, frames[12].0).unwrap(), all[12..]);
    assert!(decode(&bytes).is_err());
}

#[test]
fn an_all_static_clip_costs_one_set_and_tiny_frames() {
    let frames = clip(100, 100, 50, 2);
    let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
    let header = HEADER_BYTES + 100usize.div_ceil(8);
    let one = encode(refs(&frames[..1]), &options(1e-3)).unwrap();
    // One frame's stream: the header, the static record, an 18-byte frame, the index.
    let static_record = one.len() - header - 18 - (RECORD_HEAD + INDEX_ENTRY + INDEX_TAIL);
    assert!(
        static_record < 100 * 14 * 3,
        "{static_record} bytes for 100 Gaussians"
    );
    let expected = header + static_record + 50 * 18 + RECORD_HEAD + 50 * INDEX_ENTRY + INDEX_TAIL;
    assert_eq!(bytes.len(), expected);
    for ((_, set), (_, back)) in frames.iter().zip(decode(&bytes).unwrap()) {
        assert_within_bounds(set, &back, 1e-3);
    }
}

#[test]
fn one_frame_no_gaussians_and_no_frames_round_trip() {
    let frames = clip(5, 0, 1, 4);
    let back = decode(&encode(refs(&frames), &options(1e-3)).unwrap()).unwrap();
    assert_eq!(back.len(), 1);
    assert_within_bounds(&frames[0].1, &back[0].1, 1e-3);

    let empty = GaussianSet::default();
    let sets = [(0.0, &empty), (0.5, &empty), (1.0, &empty)];
    let back = decode(&encode(sets, &options(1e-3)).unwrap()).unwrap();
    assert_eq!(
        back,
        [
            (0.0, empty.clone()),
            (0.5, empty.clone()),
            (1.0, empty.clone())
        ]
    );

    let none = encode(std::iter::empty(), &options(1e-3)).unwrap();
    assert_eq!(none.len(), HEADER_BYTES + RECORD_HEAD + INDEX_TAIL);
    assert!(decode(&none).unwrap().is_empty());
    assert!(seek(&none, 0.0).unwrap().is_empty());
}

#[test]
fn deflate_changes_the_bytes_not_the_sets() {
    let frames = clip(64, 8, 20, 9);
    let on = encode(refs(&frames), &options(1e-3)).unwrap();
    let off = encode(
        refs(&frames),
        &EncodeOptions {
            deflate: false,
            ..options(1e-3)
        },
    )
    .unwrap();
    assert!(on.len() < off.len(), "{} against {}", on.len(), off.len());
    assert_eq!(decode(&on).unwrap(), decode(&off).unwrap());
}

#[test]
fn a_streaming_encoder_holds_masked_gaussians_and_refuses_one_that_moves_too_far() {
    let frames = clip(10, 4, 12, 6);
    let opts = options(1e-3);
    let mask = static_mask(frames.iter().map(|(_, s)| s), &opts).unwrap();
    assert_eq!(
        mask,
        [
            true, true, true, true, false, false, false, false, false, false
        ]
    );
    let (mut encoder, mut bytes) = Encoder::with_static_mask(&mask, &opts).unwrap();
    for (t, set) in &frames {
        bytes.extend(encoder.push(*t, set).unwrap());
    }
    // Gaussian 2 strays 0.9 e from its held position: still held; then 3 e: refused, and
    // the stream stays whole.
    let held = encoder.held.as_ref().unwrap()[2].position;
    let at = |x: f32| {
        let set = &frames[11].1;
        let mut p = set.positions().to_vec();
        p[2] = [x, held[1], held[2]];
        GaussianSet::new(
            p,
            set.scales().to_vec(),
            set.rotations().to_vec(),
            set.opacities().to_vec(),
            set.colors().to_vec(),
        )
        .unwrap()
    };
    let near = at(held[0] + 0.9e-3);
    bytes.extend(encoder.push(2.0, &near).unwrap());
    match encoder.push(3.0, &at(held[0] + 3e-3)).unwrap_err() {
        SceneError::InvalidGaussian { index: 2, reason } => {
            assert!(reason.contains("marked static"), "{reason}");
        }
        other => panic!("unexpected {other:?}"),
    }
    bytes.extend(encoder.finish());
    let back = decode(&bytes).unwrap();
    assert_eq!(back.len(), 13);
    assert_within_bounds(&near, &back[12].1, 1e-3);
    for ((_, set), (_, decoded)) in frames.iter().zip(&back) {
        assert_within_bounds(set, decoded, 1e-3);
    }
}

#[test]
fn a_delta_frame_needs_a_keyframe_before_it() {
    let frames = clip(4, 0, 3, 1);
    let mut bytes = encode(refs(&frames), &options(1e-3)).unwrap();
    let first = read_index(&bytes).unwrap()[0].offset as usize;
    bytes[first] = KIND_DELTA;
    assert!(reason(decode(&bytes).unwrap_err()).contains("no keyframe came before it"));
}

#[test]
fn an_index_that_lies_is_refused() {
    let frames = clip(4, 0, 3, 1);
    let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
    let at = bytes.len() - INDEX_TAIL - 2 * INDEX_ENTRY; // frame 1's time
    let mut lying = bytes.clone();
    lying[at..at + 8].copy_from_slice(&0.04f64.to_le_bytes());
    assert!(reason(decode(&lying).unwrap_err()).contains("does not list the frames"));
}

#[test]
fn every_truncation_is_an_error_and_never_a_panic() {
    let frames = clip(12, 3, 6, 10);
    let opts = EncodeOptions {
        keyframe_interval: 4,
        ..options(1e-3)
    };
    let bytes = encode(refs(&frames), &opts).unwrap();
    let all = decode(&bytes).unwrap();
    for cut in 0..bytes.len() {
        let prefix = &bytes[..cut];
        assert!(decode(prefix).is_err(), "prefix of {cut} bytes decoded");
        assert!(read_index(prefix).is_err() || seek(prefix, 0.0).is_err());
        // The incremental decoder hands out exactly the frames whose records are whole.
        let mut decoder = Decoder::new();
        decoder.feed(prefix);
        let mut got = vec![];
        while let Ok(Some(frame)) = decoder.next_frame() {
            got.push(frame);
        }
        assert_eq!(got, all[..got.len()]);
        assert!(decoder.finish().is_err());
    }
}

#[test]
fn every_corrupted_byte_is_an_error_or_valid_sets_never_a_panic() {
    let frames = clip(6, 2, 5, 12);
    let opts = EncodeOptions {
        keyframe_interval: 2,
        ..options(1e-2)
    };
    for deflate in [false, true] {
        let bytes = encode(refs(&frames), &EncodeOptions { deflate, ..opts }).unwrap();
        for at in 0..bytes.len() {
            for flip in [0x01u8, 0x80, 0xFF] {
                let mut bad = bytes.clone();
                bad[at] ^= flip;
                if let Ok(back) = decode(&bad) {
                    back.iter().for_each(|(_, s)| s.validate().unwrap());
                }
                let _ = seek(&bad, 0.1);
            }
        }
    }
}

#[test]
fn hostile_lengths_are_refused_before_anything_is_buffered_or_allocated() {
    // A header claiming u32::MAX Gaussians, and nothing else.
    let mut header = Header {
        gaussians: 0,
        static_mask: vec![],
        steps: Steps::for_error(1e-3),
    }
    .to_bytes();
    header[8..12].copy_from_slice(&u32::MAX.to_le_bytes());
    assert!(reason(decode(&header).unwrap_err()).contains("truncated"));

    // A stream of 2 moving Gaussians whose keyframe claims 4 GiB: refused on its 6 bytes.
    let frames = clip(2, 0, 2, 1);
    let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
    let first = read_index(&bytes).unwrap()[0].offset as usize;
    let mut decoder = Decoder::new();
    decoder.feed(&bytes[..first]);
    assert!(decoder.next_frame().unwrap().is_none());
    decoder.feed(&[KIND_KEYFRAME, CODING_STORED, 0xFF, 0xFF, 0xFF, 0xFF]);
    assert!(reason(decoder.next_frame().unwrap_err()).contains("claims 4294967295 bytes"));

    // A body claiming to inflate to more than 70 bytes a Gaussian.
    let mut bad = bytes.clone();
    bad[first + 14..first + 18].copy_from_slice(&1000u32.to_le_bytes());
    assert!(reason(decode(&bad).unwrap_err()).contains("it claims 1000"));

    // Steps that are not finite and positive.
    let mut bad = bytes.clone();
    bad[16..24].copy_from_slice(&f64::NAN.to_le_bytes());
    assert!(reason(decode(&bad).unwrap_err()).contains("grid steps"));
    // Another version; an unknown predictor; a mask that disagrees with S.
    for (at, value, expected) in [
        (4, 2, "version 2"),
        (6, 7, "predictor 7"),
        (12, 1, "static"),
    ] {
        let mut bad = bytes.clone();
        bad[at] = value;
        assert!(reason(decode(&bad).unwrap_err()).contains(expected));
    }
    assert!(reason(decode(b"C4GS....").unwrap_err()).contains("not a C4GV stream"));
}

#[test]
fn bytes_after_the_index_are_refused() {
    let frames = clip(2, 0, 2, 1);
    let mut bytes = encode(refs(&frames), &options(1e-3)).unwrap();
    bytes.push(0);
    assert!(reason(decode(&bytes).unwrap_err()).contains("after the index record"));
}

fn any_gaussian() -> impl Strategy<Value = (Vec<f32>, Vec<f32>, Vec<f32>, f32, Vec<f32>)> {
    let e = 1e-3f32;
    let edge = 1e6 * e;
    (
        proptest::collection::vec(-edge..=edge, 3),
        proptest::collection::vec(
            prop_oneof![
                0.0f32..1e-19,
                1e-19f32..1e3,
                proptest::num::f32::POSITIVE | proptest::num::f32::ZERO
            ],
            3,
        ),
        proptest::collection::vec(-1.0f32..1.0, 4).prop_filter("a rotation", |q| {
            q.iter().map(|v| v * v).sum::<f32>() > 1e-6
        }),
        0.0f32..=1.0,
        proptest::collection::vec(0.0f32..=COLOR_MAX, 3),
    )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    #[test]
    fn any_valid_set_round_trips_within_the_bounds(
        gaussians in proptest::collection::vec(any_gaussian(), 0..6),
        moves in proptest::collection::vec(-0.05f32..0.05, 1..5),
    ) {
        let frames: Vec<(f64, GaussianSet)> = moves
            .iter()
            .enumerate()
            .map(|(f, &by)| {
                let set = GaussianSet::new(
                    gaussians.iter().map(|g| [g.0[0], g.0[1], (g.0[2] + by).clamp(-1e3, 1e3)]).collect(),
                    gaussians.iter().map(|g| [g.1[0], g.1[1], g.1[2]]).collect(),
                    gaussians.iter().map(|g| unit(std::array::from_fn(|k| f64::from(g.2[k])))).collect(),
                    gaussians.iter().map(|g| g.3).collect(),
                    gaussians.iter().map(|g| [g.4[0], g.4[1], g.4[2]]).collect(),
                )
                .unwrap();
                (f as f64, set)
            })
            .collect();
        let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
        let back = decode(&bytes).unwrap();
        prop_assert_eq!(back.len(), frames.len());
        for ((_, set), (_, decoded)) in frames.iter().zip(&back) {
            assert_within_bounds(set, decoded, 1e-3);
        }
    }

    #[test]
    fn any_chunking_of_the_bytes_decodes_the_same_frames(
        cuts in proptest::collection::vec(0usize..2000, 0..12),
        seed in 0u64..1000,
    ) {
        let frames = clip(9, 3, 7, seed);
        let opts = EncodeOptions { keyframe_interval: 3, ..options(1e-3) };
        let bytes = encode(refs(&frames), &opts).unwrap();
        let mut cuts: Vec<usize> = cuts.into_iter().map(|c| c % (bytes.len() + 1)).collect();
        cuts.sort_unstable();
        let mut decoder = Decoder::new();
        let (mut got, mut from) = (vec![], 0);
        for cut in cuts.into_iter().chain([bytes.len()]) {
            decoder.feed(&bytes[from..cut]);
            from = cut;
            while let Some(frame) = decoder.next_frame().unwrap() {
                got.push(frame);
            }
        }
        decoder.finish().unwrap();
        prop_assert_eq!(got, decode(&bytes).unwrap());
    }

    #[test]
    fn arbitrary_bytes_never_panic(tail in proptest::collection::vec(any::<u8>(), 0..400)) {
        let frames = clip(3, 1, 2, 1);
        let bytes = encode(refs(&frames), &options(1e-3)).unwrap();
        // A real header, then anything.
        let head = HEADER_BYTES + 1;
        let _ = decode(&[&bytes[..head], &tail].concat());
        let _ = decode(&tail);
        let _ = seek(&tail, 0.0);
    }
}
