//! The Gaussian payload parsers, on payloads built by hand from the layouts in `docs/api.md` and
//! the proto.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use c4g_client::wire::{parse_binary, unpack_frame, unpack_set};
use c4g_client::{Error, GaussianSet};
use c4g_proto::v1 as proto;
use half::f16;

/// Two Gaussians, one row each of means, scales, rotations (w x y z), opacities, colours.
/// Every value is exact in f16 so both precisions compare exactly.
fn columns(shift: f32) -> [Vec<f32>; 5] {
    [
        vec![0.5 + shift, -0.25, 2.0, -1.0, 0.125, 3.5],
        vec![0.0625, 0.125, 0.25, 0.5, 0.5, 0.75],
        vec![1.0, 0.0, 0.0, 0.0, 0.0, 0.6, 0.0, 0.8],
        vec![0.75, 1.0],
        vec![0.5, 0.25, 0.0, 1.0, 0.875, 0.375],
    ]
}

fn expected_set(shift: f32) -> GaussianSet {
    GaussianSet::from_canonical(&[
        0.5 + shift,
        -0.25,
        2.0,
        0.0625,
        0.125,
        0.25,
        1.0,
        0.0,
        0.0,
        0.0,
        0.75,
        0.5,
        0.25,
        0.0, //
        -1.0,
        0.125,
        3.5,
        0.5,
        0.5,
        0.75,
        0.0,
        0.6,
        0.0,
        0.8,
        1.0,
        1.0,
        0.875,
        0.375,
    ])
    .unwrap()
}

fn f32_bytes(values: &[f32]) -> Vec<u8> {
    values.iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn f16_bytes(values: &[f32]) -> Vec<u8> {
    values
        .iter()
        .flat_map(|&v| f16::from_f32(v).to_le_bytes())
        .collect()
}

/// A `C4GS` payload: the 16-byte header, then per frame the f64 time and the five columns.
fn binary_payload(precision: u8, frames: &[(f64, [Vec<f32>; 5])], count: u32) -> Vec<u8> {
    let mut bytes = b"C4GS".to_vec();
    bytes.extend_from_slice(&1u16.to_le_bytes());
    bytes.push(precision);
    bytes.push(0);
    bytes.extend_from_slice(&(frames.len() as u32).to_le_bytes());
    bytes.extend_from_slice(&count.to_le_bytes());
    for (time, columns) in frames {
        bytes.extend_from_slice(&time.to_le_bytes());
        for column in columns {
            match precision {
                0 => bytes.extend(f32_bytes(column)),
                _ => bytes.extend(f16_bytes(column)),
            }
        }
    }
    bytes
}

#[test]
fn binary_f32_frames_parse_to_their_times_and_columns() {
    let payload = binary_payload(0, &[(0.5, columns(0.0)), (1.25, columns(1.0))], 2);
    assert_eq!(payload.len(), 16 + 2 * (8 + 2 * 14 * 4));
    let frames = parse_binary(&payload).unwrap();
    assert_eq!(frames.len(), 2);
    assert_eq!(frames[0].time, 0.5);
    assert_eq!(frames[1].time, 1.25);
    assert_eq!(frames[0].gaussians, expected_set(0.0));
    assert_eq!(frames[1].gaussians, expected_set(1.0));
    assert_eq!(frames[1].gaussians.positions()[0], [1.5, -0.25, 2.0]);
    assert_eq!(frames[0].gaussians.rotations()[1], [0.0, 0.6, 0.0, 0.8]);
    assert_eq!(frames[0].gaussians.opacities(), &[0.75, 1.0]);
}

#[test]
fn binary_f16_values_widen_to_f32() {
    let payload = binary_payload(1, &[(2.0, columns(0.0))], 2);
    assert_eq!(payload.len(), 16 + 8 + 2 * 14 * 2);
    let frames = parse_binary(&payload).unwrap();
    assert_eq!(frames.len(), 1);
    assert_eq!(frames[0].time, 2.0);
    // 0.6 and 0.8 are not exact in f16: they come back as the nearest halves.
    let set = &frames[0].gaussians;
    assert_eq!(set.rotations()[1][1], f16::from_f32(0.6).to_f32());
    assert!((set.rotations()[1][1] - 0.6).abs() < 1e-3);
    assert_eq!(set.positions(), expected_set(0.0).positions());
    assert_eq!(set.colors(), expected_set(0.0).colors());
}

#[test]
fn binary_with_no_frames_or_no_gaussians_is_valid() {
    assert!(parse_binary(&binary_payload(0, &[], 5)).unwrap().is_empty());
    let empty: [Vec<f32>; 5] = Default::default();
    let frames = parse_binary(&binary_payload(1, &[(0.0, empty)], 0)).unwrap();
    assert_eq!(frames.len(), 1);
    assert!(frames[0].gaussians.is_empty());
}

#[test]
fn binary_payloads_that_break_the_layout_are_malformed() {
    let good = binary_payload(0, &[(0.5, columns(0.0))], 2);
    let mut cases: Vec<(&str, Vec<u8>)> = vec![
        ("short header", good[..10].to_vec()),
        ("truncated", good[..good.len() - 1].to_vec()),
        ("trailing byte", [&good[..], &[0]].concat()),
    ];
    let mut bad_magic = good.clone();
    bad_magic[0] = b'X';
    cases.push(("magic", bad_magic));
    let mut bad_version = good.clone();
    bad_version[4] = 2;
    cases.push(("version", bad_version));
    let mut bad_precision = good.clone();
    bad_precision[6] = 7;
    cases.push(("precision", bad_precision));
    let mut huge = good.clone();
    huge[8..16].copy_from_slice(&[0xff; 8]);
    cases.push(("huge counts", huge));
    for (what, payload) in cases {
        match parse_binary(&payload) {
            Err(Error::Malformed(_)) => {}
            other => panic!("{what}: expected Malformed, got {other:?}"),
        }
    }
}

fn proto_set(precision: proto::Precision, count: u32, shift: f32) -> proto::GaussianSet {
    let pack = |values: &Vec<f32>| match precision {
        proto::Precision::F16 => f16_bytes(values),
        _ => f32_bytes(values),
    };
    let [means, scales, rotations, opacities, colors] = columns(shift);
    proto::GaussianSet {
        count,
        precision: precision.into(),
        means: pack(&means),
        scales: pack(&scales),
        rotations: pack(&rotations),
        opacities: pack(&opacities),
        colors: pack(&colors),
        ..Default::default()
    }
}

#[test]
fn proto_sets_unpack_in_either_precision() {
    for precision in [proto::Precision::Unspecified, proto::Precision::F32] {
        let set = unpack_set(&proto_set(precision, 2, 0.0)).unwrap();
        assert_eq!(set, expected_set(0.0), "{precision:?}");
    }
    let set = unpack_set(&proto_set(proto::Precision::F16, 2, 0.0)).unwrap();
    assert_eq!(set.positions(), expected_set(0.0).positions());
    assert_eq!(set.rotations()[1][3], f16::from_f32(0.8).to_f32());
}

#[test]
fn proto_frames_keep_their_time() {
    let frame = proto::GaussianFrame {
        time: 0.75,
        gaussians: Some(proto_set(proto::Precision::F32, 2, 0.5)),
        ..Default::default()
    };
    let frame = unpack_frame(&frame).unwrap();
    assert_eq!(frame.time, 0.75);
    assert_eq!(frame.gaussians, expected_set(0.5));

    let missing = proto::GaussianFrame {
        time: 0.75,
        gaussians: None,
        ..Default::default()
    };
    assert!(matches!(unpack_frame(&missing), Err(Error::Malformed(_))));
}

#[test]
fn proto_arrays_of_the_wrong_length_name_the_array() {
    let mut set = proto_set(proto::Precision::F32, 2, 0.0);
    set.scales.pop();
    match unpack_set(&set) {
        Err(Error::Malformed(message)) => assert!(message.contains("scales"), "{message}"),
        other => panic!("expected Malformed, got {other:?}"),
    }
    // The count says 3, the arrays hold 2.
    let set = proto_set(proto::Precision::F32, 3, 0.0);
    assert!(matches!(unpack_set(&set), Err(Error::Malformed(_))));
    // f16 arrays read as f32 are half as long as they should be.
    let mut set = proto_set(proto::Precision::F16, 2, 0.0);
    set.precision = proto::Precision::F32.into();
    assert!(matches!(unpack_set(&set), Err(Error::Malformed(_))));
    let mut set = proto_set(proto::Precision::F32, 2, 0.0);
    set.precision = 9;
    assert!(matches!(unpack_set(&set), Err(Error::Malformed(_))));
}
