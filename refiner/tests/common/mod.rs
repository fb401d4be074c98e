//! Shared helpers of the refiner's integration tests: where the fixture package is, whether ONNX
//! Runtime is available, reading the reference archives, and comparing arrays.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

pub mod external;

use std::fs::File;
use std::path::PathBuf;

use ndarray::ArrayD;
use ndarray_npy::NpzReader;

pub fn fixture_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../models/fixtures/wan-vace-tiny")
}

pub fn reference_dir() -> PathBuf {
    fixture_dir().join("reference")
}

/// The same models in C4G's layout (3 keyframes, 5 rendered frames), with its own references.
pub fn c4g_fixture_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../models/fixtures/wan-vace-tiny-c4g")
}

/// Why the tests that need the fixture cannot run here, if they cannot. Outside CI a missing
/// piece skips the test with a message; in CI (`CI` set) it fails, so a misconfigured CI cannot
/// pass by running nothing.
pub fn fixture_skip_reason() -> Option<String> {
    let reason = (!fixture_dir().join("refiner.json").is_file())
        .then(|| format!("fixture package {} not found", fixture_dir().display()));
    report(reason)
}

/// Like [`fixture_skip_reason`], and ONNX Runtime must be configured too.
pub fn skip_reason() -> Option<String> {
    let reason = if std::env::var_os("ORT_DYLIB_PATH").is_none_or(|p| p.is_empty()) {
        Some(
            "ORT_DYLIB_PATH is not set (point it at libonnxruntime.so from the onnxruntime wheel)"
                .to_owned(),
        )
    } else if !fixture_dir().join("refiner.json").is_file() {
        Some(format!(
            "fixture package {} not found",
            fixture_dir().display()
        ))
    } else {
        None
    };
    report(reason)
}

fn report(reason: Option<String>) -> Option<String> {
    if let Some(reason) = &reason {
        assert!(
            std::env::var_os("CI").is_none(),
            "in CI every refiner test must run: {reason}"
        );
        eprintln!("skipped: {reason}");
    }
    reason
}

/// A reference archive under `reference/`.
pub struct Npz(NpzReader<File>);

impl Npz {
    pub fn open(name: &str) -> Self {
        Self::open_in(&fixture_dir(), name)
    }

    /// An archive under `package/reference/`.
    pub fn open_in(package: &std::path::Path, name: &str) -> Self {
        let path = package.join("reference").join(name);
        Self(
            NpzReader::new(File::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())))
                .unwrap(),
        )
    }

    pub fn array(&mut self, name: &str) -> ArrayD<f32> {
        self.0
            .by_name(name)
            .unwrap_or_else(|e| panic!("{name}: {e}"))
    }

    /// The array flattened in its (C) order.
    pub fn vec(&mut self, name: &str) -> Vec<f32> {
        let a = self.array(name);
        a.as_standard_layout().iter().copied().collect()
    }

    /// Entry `i` along the first axis, flattened.
    pub fn row(&mut self, name: &str, i: usize) -> Vec<f32> {
        let a = self.array(name);
        let a = a.as_standard_layout();
        let row = a.len() / a.shape()[0];
        a.iter().skip(i * row).take(row).copied().collect()
    }

    pub fn int(&mut self, name: &str) -> i64 {
        self.ints(name)[0]
    }

    pub fn ints(&mut self, name: &str) -> Vec<i64> {
        let a: ArrayD<i64> = self
            .0
            .by_name(name)
            .unwrap_or_else(|e| panic!("{name}: {e}"));
        a.iter().copied().collect()
    }

    pub fn scalar(&mut self, name: &str) -> f32 {
        self.vec(name)[0]
    }
}

/// Largest absolute difference and largest |reference| of two arrays.
pub fn max_abs_diff(got: &[f32], expected: &[f32]) -> (f32, f32) {
    assert_eq!(got.len(), expected.len(), "lengths differ");
    let diff = got
        .iter()
        .zip(expected)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    let scale = expected.iter().map(|v| v.abs()).fold(0.0f32, f32::max);
    (diff, scale)
}

/// Asserts `|got − expected| ≤ atol + rtol·|expected|` element-wise, printing the worst error.
pub fn assert_close(got: &[f32], expected: &[f32], atol: f32, rtol: f32, what: &str) {
    assert_eq!(got.len(), expected.len(), "{what}: lengths differ");
    let mut worst = (0.0f32, 0usize);
    for (i, (a, b)) in got.iter().zip(expected).enumerate() {
        assert!(a.is_finite(), "{what}: element {i} is {a}");
        let excess = (a - b).abs() - (atol + rtol * b.abs());
        if excess > worst.0 {
            worst = (excess, i);
        }
    }
    let (diff, scale) = max_abs_diff(got, expected);
    eprintln!("{what}: max |error| {diff:.3e} (max |reference| {scale:.3e})");
    let i = worst.1;
    assert!(
        worst.0 <= 0.0,
        "{what}: element {i} is {} but the reference is {} (tolerance {atol:e} + {rtol:e}·|ref|)",
        got[i],
        expected[i]
    );
}
