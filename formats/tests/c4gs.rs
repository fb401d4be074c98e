//! The `C4GS` codec: random valid sets round-trip at both precisions (exactly in `f32`, within
//! half precision's rounding in `f16`), and no byte string, however hostile or damaged, makes the
//! reader panic or allocate beyond the payload.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use c4g_formats::c4gs::{self, HEADER_BYTES, Precision};
use c4g_scene::GaussianSet;
use proptest::prelude::*;

/// Finite values spanning many binades, inside `f16`'s range (±65504) so the `f16` round trip
/// stays finite, with zero and values small enough to be `f16` subnormals (below 2⁻¹⁴).
fn value() -> impl Strategy<Value = f32> {
    prop_oneof![
        Just(0.0f32),
        -1e4f32..1e4f32,
        -1.0f32..1.0f32,
        -1e-5f32..1e-5f32,
    ]
}

fn non_negative() -> impl Strategy<Value = f32> {
    value().prop_map(f32::abs)
}

/// A unit quaternion (as `GaussianSet::validate` requires): a random direction, normalised.
fn rotation() -> impl Strategy<Value = [f32; 4]> {
    prop::array::uniform4(-1.0f32..1.0f32).prop_map(|q| {
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        if norm < 1e-3 {
            [1.0, 0.0, 0.0, 0.0]
        } else {
            q.map(|v| v / norm)
        }
    })
}

/// A valid set of `count` Gaussians.
fn set(count: usize) -> impl Strategy<Value = GaussianSet> {
    (
        prop::collection::vec(prop::array::uniform3(value()), count),
        prop::collection::vec(prop::array::uniform3(non_negative()), count),
        prop::collection::vec(rotation(), count),
        prop::collection::vec(0.0f32..=1.0f32, count),
        prop::collection::vec(prop::array::uniform3(non_negative()), count),
    )
        .prop_map(|(positions, scales, rotations, opacities, colors)| {
            let set = GaussianSet::new(positions, scales, rotations, opacities, colors).unwrap();
            set.validate().unwrap();
            set
        })
}

/// 0..4 frames of one random count in 0..64, at finite times.
fn frames() -> impl Strategy<Value = Vec<(f64, GaussianSet)>> {
    (0usize..64, 0usize..4).prop_flat_map(|(count, frames)| {
        prop::collection::vec((-1e6f64..1e6f64, set(count)), frames)
    })
}

fn encode(frames: &[(f64, GaussianSet)], precision: Precision) -> Vec<u8> {
    c4gs::encode(frames.iter().map(|(t, s)| (*t, s)), precision).unwrap()
}

/// Every value of a set, column by column.
fn values(set: &GaussianSet) -> Vec<f32> {
    let mut out: Vec<f32> = set.positions().iter().flatten().copied().collect();
    out.extend(set.scales().iter().flatten());
    out.extend(set.rotations().iter().flatten());
    out.extend(set.opacities());
    out.extend(set.colors().iter().flatten());
    out
}

/// Round to nearest: a normal `f16` (11 significant bits) is within half an ulp, 2⁻¹¹ of the
/// value; below 2⁻¹⁴ the `f16` spacing is fixed at 2⁻²⁴, so the error there is at most 2⁻²⁵.
fn within_f16_rounding(got: f32, want: f32) -> bool {
    (got - want).abs() <= want.abs() * 2f32.powi(-11) + 2f32.powi(-25)
}

proptest! {
    #[test]
    fn f32_round_trips_exactly(frames in frames()) {
        let bytes = encode(&frames, Precision::F32);
        let count = frames.first().map_or(0, |(_, s)| s.len());
        prop_assert_eq!(bytes.len(), HEADER_BYTES + frames.len() * (8 + count * 14 * 4));
        prop_assert_eq!(c4gs::decode(&bytes).unwrap(), frames);
    }

    #[test]
    fn f16_round_trips_within_half_precision_rounding(frames in frames()) {
        let bytes = encode(&frames, Precision::F16);
        let count = frames.first().map_or(0, |(_, s)| s.len());
        prop_assert_eq!(bytes.len(), HEADER_BYTES + frames.len() * (8 + count * 14 * 2));
        let back = c4gs::decode(&bytes).unwrap();
        prop_assert_eq!(back.len(), frames.len());
        for ((t, set), (t_back, set_back)) in frames.iter().zip(&back) {
            // Times are f64 in either precision.
            prop_assert_eq!(t, t_back);
            prop_assert_eq!(set_back.len(), set.len());
            for (got, want) in values(set_back).into_iter().zip(values(set)) {
                prop_assert!(within_f16_rounding(got, want), "{} for {}", got, want);
            }
            // Each rotation component moves by at most 2⁻¹¹ of itself, so the norm does too:
            // inside the set's 1e-3 tolerance, and the other invariants survive rounding.
            set_back.validate().unwrap();
        }
    }

}

proptest! {
    // Decoding a damaged payload is cheap: many more cases than the round trips.
    #![proptest_config(ProptestConfig::with_cases(1024))]

    #[test]
    fn random_bytes_never_panic(bytes in prop::collection::vec(any::<u8>(), 0..256)) {
        let _ = c4gs::decode(&bytes);
    }

    #[test]
    fn random_headers_never_panic(
        precision in 0u8..3,
        frames in any::<u32>(),
        count in any::<u32>(),
        body in prop::collection::vec(any::<u8>(), 0..512),
    ) {
        let mut bytes = b"C4GS\x01\x00".to_vec();
        bytes.push(precision);
        bytes.push(0);
        bytes.extend_from_slice(&frames.to_le_bytes());
        bytes.extend_from_slice(&count.to_le_bytes());
        bytes.extend_from_slice(&body);
        let _ = c4gs::decode(&bytes);
    }

    #[test]
    fn damaged_payloads_never_panic(
        frames in frames(),
        f16 in any::<bool>(),
        flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 0..8),
        cut in any::<prop::sample::Index>(),
        truncate in any::<bool>(),
    ) {
        let precision = if f16 { Precision::F16 } else { Precision::F32 };
        let mut bytes = encode(&frames, precision);
        for (at, value) in flips {
            let at = at.index(bytes.len());
            bytes[at] = value;
        }
        if truncate {
            bytes.truncate(cut.index(bytes.len() + 1));
        }
        let _ = c4gs::decode(&bytes);
    }
}

/// A header with this frame count and N over an `f32` body of `body` bytes.
fn header(frames: u32, count: u32, body: usize) -> Vec<u8> {
    let mut bytes = b"C4GS\x01\x00\x00\x00".to_vec();
    bytes.extend_from_slice(&frames.to_le_bytes());
    bytes.extend_from_slice(&count.to_le_bytes());
    bytes.resize(HEADER_BYTES + body, 0);
    bytes
}

#[test]
fn huge_header_counts_are_refused_before_any_allocation() {
    // Allocating for what these claim (4e9 frames, or 4e9 Gaussians a frame) would abort the
    // test binary; they must fail on the length check instead.
    for (frames, count) in [
        (4_000_000_000, 0),
        (u32::MAX, 1),
        (1, u32::MAX),
        (u32::MAX, u32::MAX),
    ] {
        let err = c4gs::decode(&header(frames, count, 64))
            .unwrap_err()
            .to_string();
        // "needs N bytes; got 80", or "too large" where N overflows.
        assert!(err.contains("needs") || err.contains("too large"), "{err}");
    }
}

#[test]
fn errors_say_what_is_short() {
    let cases = [
        (vec![0u8; 10], "16-byte header; got 10 bytes"),
        (b"PLY\n".repeat(4), "not a C4GS payload"),
        (header(1, 2, 8 + 2 * 14 * 4 - 1), "needs 136 bytes; got 135"),
        (header(0, 0, 1), "needs 16 bytes; got 17"),
    ];
    for (bytes, says) in cases {
        let err = c4gs::decode(&bytes).unwrap_err().to_string();
        assert!(err.contains(says), "{err}");
    }
    let mut bytes = header(0, 0, 0);
    bytes[6] = 2;
    let err = c4gs::decode(&bytes).unwrap_err().to_string();
    assert!(err.contains("precision code 2"), "{err}");
}

#[test]
fn unpacked_columns_name_the_one_that_is_off() {
    // Values exact in f16, so the set comes back equal.
    let set = GaussianSet::from_canonical(&[
        1.0, 2.0, 3.0, 0.125, 0.25, 0.375, 1.0, 0.0, 0.0, 0.0, 0.5, 0.25, 0.5, 1.0,
    ])
    .unwrap();
    let mut columns = c4gs::pack_columns(&set, Precision::F16);
    let [m, s, r, o, c] = &columns;
    assert_eq!(
        c4gs::unpack_columns(1, Precision::F16, [m, s, r, o, c]).unwrap(),
        set
    );
    columns[3].push(0);
    let [m, s, r, o, c] = &columns;
    let err = c4gs::unpack_columns(1, Precision::F16, [m, s, r, o, c]).unwrap_err();
    assert!(
        err.to_string()
            .contains("opacities of 1 f16 Gaussians needs 2 bytes; got 3"),
        "{err}"
    );
    let err = c4gs::unpack_columns(usize::MAX, Precision::F32, [&[]; 5]).unwrap_err();
    assert!(err.to_string().contains("too many"), "{err}");
}

#[test]
fn zero_frames_and_zero_gaussians_round_trip() {
    for precision in [Precision::F32, Precision::F16] {
        let none = encode(&[], precision);
        assert_eq!(none.len(), HEADER_BYTES);
        assert!(c4gs::decode(&none).unwrap().is_empty());
        let empty = vec![
            (0.25, GaussianSet::default()),
            (0.5, GaussianSet::default()),
        ];
        let bytes = encode(&empty, precision);
        assert_eq!(bytes.len(), HEADER_BYTES + 2 * 8);
        assert_eq!(c4gs::decode(&bytes).unwrap(), empty);
    }
}
