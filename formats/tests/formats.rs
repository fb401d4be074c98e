//! Files written by other tools, built byte by byte here from the formats' descriptions (not
//! with our writers), read back as intended; malformed ones fail with errors that say why.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use c4g_formats::{ply, splat};
use c4g_scene::{GaussianSet, SceneError};

const C0: f64 = 0.282_094_791_773_878_14;

fn logit(o: f64) -> f64 {
    (o / (1.0 - o)).ln()
}

/// The values of one Gaussian as a trainer stores them, by property name.
fn stored(i: usize) -> Vec<(&'static str, f64)> {
    let i = i as f64;
    vec![
        ("x", 0.5 + i),
        ("y", -1.25),
        ("z", 3.0 * (i + 1.0)),
        ("f_dc_0", (0.2 - 0.5) / C0),
        ("f_dc_1", (0.6 - 0.5) / C0),
        ("f_dc_2", (1.0 - 0.5) / C0),
        ("opacity", logit(0.8)),
        ("scale_0", 0.05f64.ln()),
        ("scale_1", 0.1f64.ln()),
        ("scale_2", (0.2 * (i + 1.0)).ln()),
        // Not normalised (norm 2), as trainers leave them.
        ("rot_0", 1.0),
        ("rot_1", 1.0),
        ("rot_2", -1.0),
        ("rot_3", 1.0),
    ]
}

fn check(set: &GaussianSet, n: usize) {
    assert_eq!(set.len(), n);
    for i in 0..n {
        let close = |a: f32, b: f64| assert!((f64::from(a) - b).abs() < 1e-5, "{a} vs {b}");
        let p = set.positions()[i];
        close(p[0], 0.5 + i as f64);
        close(p[1], -1.25);
        close(p[2], 3.0 * (i as f64 + 1.0));
        let c = set.colors()[i];
        close(c[0], 0.2);
        close(c[1], 0.6);
        close(c[2], 1.0);
        close(set.opacities()[i], 0.8);
        let s = set.scales()[i];
        close(s[0], 0.05);
        close(s[1], 0.1);
        close(s[2], 0.2 * (i as f64 + 1.0));
        for (q, want) in set.rotations()[i].iter().zip([0.5, 0.5, -0.5, 0.5]) {
            close(*q, want);
        }
    }
    set.validate().unwrap();
}

#[test]
fn a_hand_built_binary_ply_in_another_property_order_with_extras_reads_as_intended() {
    // Rotation first, then opacity, doubles for positions, normals and f_rest in between, a
    // uchar we do not know, a face element after the vertices.
    let order = [
        ("float", "rot_0"),
        ("float", "rot_1"),
        ("float", "rot_2"),
        ("float", "rot_3"),
        ("float", "opacity"),
        ("double", "x"),
        ("double", "y"),
        ("double", "z"),
        ("float", "nx"),
        ("float", "ny"),
        ("float", "nz"),
        ("float", "f_dc_0"),
        ("float", "f_dc_1"),
        ("float", "f_dc_2"),
        ("float", "f_rest_0"),
        ("float", "f_rest_1"),
        ("uchar", "flags"),
        ("float", "scale_0"),
        ("float", "scale_1"),
        ("float", "scale_2"),
    ];
    let mut bytes =
        b"ply\nformat binary_little_endian 1.0\ncomment hand made\nelement vertex 2\n".to_vec();
    for (ty, name) in order {
        bytes.extend(format!("property {ty} {name}\n").as_bytes());
    }
    bytes.extend(b"element face 1\nproperty list uchar int vertex_indices\nend_header\n");
    for i in 0..2 {
        let values = stored(i);
        let value = |name: &str| values.iter().find(|(n, _)| *n == name).map_or(0.0, |v| v.1);
        for (ty, name) in order {
            match ty {
                "double" => bytes.extend(value(name).to_le_bytes()),
                "uchar" => bytes.push(7),
                _ => bytes.extend((value(name) as f32).to_le_bytes()),
            }
        }
    }
    bytes.extend([3u8]);
    for v in [0i32, 1, 0] {
        bytes.extend(v.to_le_bytes());
    }
    check(&ply::decode(&bytes).unwrap(), 2);
}

#[test]
fn an_ascii_ply_reads_as_intended() {
    let names: Vec<&str> = stored(0).iter().map(|(n, _)| *n).collect();
    let mut text = String::from("ply\r\nformat ascii 1.0\r\nelement vertex 3\r\n");
    for name in &names {
        text.push_str(&format!("property float {name}\r\n"));
    }
    text.push_str("end_header\r\n");
    for i in 0..3 {
        let row: Vec<String> = stored(i).iter().map(|(_, v)| format!("{v}")).collect();
        text.push_str(&row.join(" "));
        text.push('\n');
    }
    check(&ply::decode(text.as_bytes()).unwrap(), 3);
}

#[test]
fn a_big_endian_ply_with_a_leading_element_reads_as_intended() {
    let mut bytes =
        b"ply\nformat binary_big_endian 1.0\nelement camera 1\nproperty list ushort float k\nproperty short id\nelement vertex 1\n"
            .to_vec();
    for (name, _) in stored(0) {
        bytes.extend(format!("property float {name}\n").as_bytes());
    }
    bytes.extend(b"end_header\n");
    bytes.extend(2u16.to_be_bytes());
    bytes.extend(1.5f32.to_be_bytes());
    bytes.extend(2.5f32.to_be_bytes());
    bytes.extend((-3i16).to_be_bytes());
    for (_, v) in stored(0) {
        bytes.extend((v as f32).to_be_bytes());
    }
    check(&ply::decode(&bytes).unwrap(), 1);
}

#[test]
fn feature_columns_read_back_in_order() {
    let mut bytes = b"ply\nformat binary_little_endian 1.0\nelement vertex 1\n".to_vec();
    // feat_1 before feat_0: the index in the name, not the position, decides.
    let names: Vec<&str> = stored(0)
        .iter()
        .map(|(n, _)| *n)
        .chain(["feat_1", "feat_0"])
        .collect();
    for name in &names {
        bytes.extend(format!("property float {name}\n").as_bytes());
    }
    bytes.extend(b"end_header\n");
    for (_, v) in stored(0) {
        bytes.extend((v as f32).to_le_bytes());
    }
    bytes.extend(11.0f32.to_le_bytes());
    bytes.extend(10.0f32.to_le_bytes());
    let set = ply::decode(&bytes).unwrap();
    assert_eq!(set.features().unwrap().row(0), Some(&[10.0, 11.0][..]));
}

fn reason(bytes: &[u8]) -> String {
    match ply::decode(bytes) {
        Err(SceneError::Format {
            format: "ply",
            reason,
        }) => reason,
        other => panic!("expected a ply format error, got {other:?}"),
    }
}

fn minimal_header(format: &str, count: usize) -> Vec<u8> {
    let mut bytes = format!("ply\nformat {format} 1.0\nelement vertex {count}\n").into_bytes();
    for (name, _) in stored(0) {
        bytes.extend(format!("property float {name}\n").as_bytes());
    }
    bytes.extend(b"end_header\n");
    bytes
}

#[test]
fn truncated_and_malformed_files_fail_with_reasons() {
    let mut truncated = minimal_header("binary_little_endian", 2);
    truncated.extend([0u8; 14 * 4 + 3]);
    assert!(
        reason(&truncated).contains("truncated"),
        "{}",
        reason(&truncated)
    );

    let huge = minimal_header("binary_little_endian", usize::MAX / 8);
    assert!(reason(&huge).contains("truncated"));

    let mut short_ascii = minimal_header("ascii", 2);
    short_ascii.extend(b"1 2 3 4 5 6 7 8 9 10 11 12 13 14\n1 2 3\n");
    let r = reason(&short_ascii);
    assert!(r.contains("vertex 1") && r.contains("ends"), "{r}");

    let mut not_a_number = minimal_header("ascii", 1);
    not_a_number.extend(b"1 2 3 4 5 6 seven 8 9 10 11 12 13 14\n");
    assert!(reason(&not_a_number).contains("`seven` is not a number"));

    assert!(reason(b"PK\x03\x04 a zip").contains("end_header"));
    assert!(reason(b"hello\nend_header\n").contains("start with `ply`"));
    assert!(reason(b"ply\nelement vertex 1\nproperty float x\nend_header\n").contains("format"));
    assert!(
        reason(b"ply\nformat binary_middle_endian 1.0\nend_header\n").contains("unknown format")
    );
    assert!(
        reason(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty quad x\nend_header\n")
            .contains("unknown type")
    );
    let r = reason(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n");
    assert!(r.contains("no `y` property"), "{r}");
    assert!(reason(b"ply\nformat ascii 1.0\nelement face 0\nend_header\n").contains("no `vertex`"));
}

#[test]
fn ply_and_splat_files_round_trip_on_disk() {
    let set = GaussianSet::new(
        vec![[0.0, 1.0, 2.0]],
        vec![[0.1, 0.2, 0.3]],
        vec![[1.0, 0.0, 0.0, 0.0]],
        vec![0.75],
        vec![[0.1, 0.2, 0.3]],
    )
    .unwrap();
    let dir = std::env::temp_dir().join(format!("c4g-formats-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    ply::write(&dir.join("a.ply"), &set).unwrap();
    splat::write(&dir.join("a.splat"), &set).unwrap();
    let from_ply = ply::read(&dir.join("a.ply")).unwrap();
    let from_splat = splat::read(&dir.join("a.splat")).unwrap();
    assert_eq!(from_ply.positions(), set.positions());
    assert_eq!(from_splat.positions(), set.positions());
    assert!((from_ply.opacities()[0] - 0.75).abs() < 1e-6);
    assert!((from_splat.opacities()[0] - 0.75).abs() <= 1.0 / 510.0);
    let missing = ply::read(&dir.join("missing.ply")).unwrap_err();
    assert!(matches!(missing, SceneError::Io { .. }), "{missing}");
    std::fs::remove_dir_all(&dir).unwrap();
}

proptest::proptest! {
    #![proptest_config(proptest::prelude::ProptestConfig::with_cases(64))]

    /// Any valid set survives our writer and reader within the tolerances stated in `ply`:
    /// positions and features exact, rotations, opacities and colours within 1e-6 absolute,
    /// scales within 2e-6 relative.
    #[test]
    fn ply_round_trips_within_its_stated_tolerances(
        rows in proptest::collection::vec(
            (
                proptest::array::uniform3(-1e4f32..1e4),
                proptest::array::uniform3(1e-6f32..1e3),
                proptest::array::uniform4(-1f32..1.0),
                0f32..=1.0,
                proptest::array::uniform3(0f32..1.5),
                proptest::array::uniform2(-10f32..10.0),
            ),
            0..20,
        )
    ) {
        let unit = |q: [f32; 4]| {
            let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
            if n > 1e-3 { q.map(|v| v / n) } else { [1.0, 0.0, 0.0, 0.0] }
        };
        let set = GaussianSet::new(
            rows.iter().map(|r| r.0).collect(),
            rows.iter().map(|r| r.1).collect(),
            rows.iter().map(|r| unit(r.2)).collect(),
            rows.iter().map(|r| r.3).collect(),
            rows.iter().map(|r| r.4).collect(),
        )
        .unwrap()
        .with_features(
            c4g_scene::FeatureBlock::new(2, rows.iter().flat_map(|r| r.5).collect()).unwrap(),
        )
        .unwrap();
        let back = ply::decode(&ply::encode(&set)).unwrap();
        proptest::prop_assert_eq!(back.positions(), set.positions());
        proptest::prop_assert_eq!(back.features(), set.features());
        for i in 0..set.len() {
            proptest::prop_assert!((back.opacities()[i] - set.opacities()[i]).abs() <= 1e-6);
            for k in 0..3 {
                let (a, b) = (back.scales()[i][k], set.scales()[i][k]);
                proptest::prop_assert!((a - b).abs() <= 2e-6 * b, "{} vs {}", a, b);
                proptest::prop_assert!((back.colors()[i][k] - set.colors()[i][k]).abs() <= 1e-6);
            }
            for k in 0..4 {
                proptest::prop_assert!((back.rotations()[i][k] - set.rotations()[i][k]).abs() <= 1e-6);
            }
        }
    }
}
