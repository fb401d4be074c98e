//! Lower-precision packages through the Rust engine: c4g-tiny converted to f16 and int8 by the
//! export tool's converter (`python -m c4g.precision`, run here into a temporary directory) loads,
//! decodes a real test clip into valid (finite, in-range) sets close to the f32 package's, and a
//! package whose graphs and `model.json` disagree on their precision is refused at load.
//!
//! Tolerances are the converter's own test's (models/python/tests/test_precision.py), measured on
//! this clip: f16 5e-3 in position and colour, int8 0.1 (the scene spans about 1.2 units).
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use c4g_engine::{Engine, EngineError, EngineOptions};
use c4g_renderer::GaussianSet;

/// The Python environment that has the converter, or `None` (allowed only outside CI).
fn python() -> Option<PathBuf> {
    let python = std::env::var_os("PYTHON").map(PathBuf::from);
    let usable = python.as_ref().is_some_and(|p| p.exists())
        && std::env::var_os("ORT_DYLIB_PATH").is_some_and(|p| !p.is_empty());
    if !usable {
        assert!(
            std::env::var_os("CI").is_none(),
            "in CI PYTHON and ORT_DYLIB_PATH must be set (scripts/env.sh)"
        );
        eprintln!("skipped: PYTHON (scripts/env.sh) or ORT_DYLIB_PATH is not set");
        return None;
    }
    python
}

fn convert(python: &Path, precision: &str, out: &Path) {
    let status = Command::new(python)
        .args(["-m", "c4g.precision", "--package"])
        .arg(common::tiny_dir())
        .args(["--precision", precision, "--out"])
        .arg(out)
        .env("PYTHONPATH", common::workspace().join("models/python"))
        .status()
        .unwrap();
    assert!(status.success(), "the converter failed for {precision}");
}

fn decode(engine: &Engine) -> Vec<GaussianSet> {
    let clip = common::tiny_clip(engine, "seed-2000000");
    let encoding = engine.encode(&clip.context).unwrap();
    engine
        .decode(&encoding, &[0.0, 0.1, 0.3, 0.55, 0.6])
        .unwrap()
}

fn max_difference(a: &[[f32; 3]], b: &[[f32; 3]]) -> f32 {
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

#[test]
fn f16_and_int8_packages_decode_valid_sets_close_to_f32() {
    let Some(python) = python() else { return };
    let exact = decode(&Engine::load(common::tiny_dir(), EngineOptions::default()).unwrap());
    for (precision, bound) in [("f16", 5e-3), ("int8", 0.1)] {
        let dir = tempfile::tempdir().unwrap();
        convert(&python, precision, dir.path());
        let engine = Engine::load(dir.path(), EngineOptions::default()).unwrap();
        assert_eq!(engine.manifest().precision, precision);
        // `decode` validates every set: finite values, unit rotations, opacities in [0, 1].
        let sets = decode(&engine);
        for (got, want) in sets.iter().zip(&exact) {
            let position = max_difference(got.positions(), want.positions());
            let colour = max_difference(got.colors(), want.colors());
            assert!(
                position < bound,
                "{precision}: position differs by {position}"
            );
            assert!(colour < bound, "{precision}: colour differs by {colour}");
        }
    }
}

#[test]
fn graphs_and_manifest_that_disagree_on_precision_are_refused() {
    let Some(python) = python() else { return };
    let dir = tempfile::tempdir().unwrap();
    convert(&python, "int8", dir.path());
    let manifest = dir.path().join("model.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    std::fs::write(
        &manifest,
        text.replace("\"precision\": \"int8\"", "\"precision\": \"f32\""),
    )
    .unwrap();
    let err = Engine::load(dir.path(), EngineOptions::default()).unwrap_err();
    assert!(matches!(err, EngineError::InvalidPackage { .. }), "{err}");
    let message = err.to_string();
    assert!(
        message.contains("computes in int8") && message.contains("c4g.precision"),
        "{message}"
    );
}
