//! Lower-precision packages through the Rust engine: c4g-tiny converted to f16 and int8 by the
//! export tool's converter (`python -m c4g.package.precision`, run here into a temporary directory) loads,
//! decodes a real test clip into valid (finite, in-range) sets close to the f32 package's, and a
//! package whose graphs and `model.json` disagree on their precision is refused at load.
//!
//! Tolerances, measured on this clip with margin: f16 5e-3 in colour and in position relative to
//! each Gaussian's distance from the camera, int8 0.1 in colour and 0.05 of the distance. Position
//! errors are relative because they grow with depth (a Gaussian is its ray times its depth), and
//! c4g-tiny v2 puts a wall 10 units away: absolute, int8's error there was 0.133 on one CPU (AMD
//! EPYC) and under 0.1 on another, so an absolute bound tested the CPU's int8 kernels.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};
use std::process::Command;

use c4g_engine::{Engine, EngineError, EngineOptions};
use c4g_scene::GaussianSet;

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
        .args(["-m", "c4g.package.precision", "--package"])
        .arg(common::tiny_dir())
        .args(["--precision", precision, "--out"])
        .arg(out)
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

/// The largest position difference, each Gaussian's taken relative to its distance from the
/// camera (at least 1 unit): lower precision perturbs the decoder's activations by a fraction of
/// their range, and a Gaussian's position is its ray times its depth, so its error grows with
/// its depth (c4g-tiny v2 has Gaussians 10 units away, on the far wall).
fn max_relative_position_difference(got: &[[f32; 3]], want: &[[f32; 3]]) -> f32 {
    got.iter()
        .zip(want)
        .map(|(g, w)| {
            let d = (0..3).map(|k| (g[k] - w[k]).powi(2)).sum::<f32>().sqrt();
            d / (0..3).map(|k| w[k].powi(2)).sum::<f32>().sqrt().max(1.0)
        })
        .fold(0.0, f32::max)
}

#[test]
fn f16_and_int8_packages_decode_valid_sets_close_to_f32() {
    let Some(python) = python() else { return };
    let exact = decode(&Engine::load(common::tiny_dir(), EngineOptions::default()).unwrap());
    // (precision, position bound relative to each Gaussian's distance, colour bound); measured
    // on this clip 8e-4 / 1.7e-3 (f16) and 0.023 / 0.059 (int8), AMD EPYC.
    for (precision, bound, colour_bound) in [("f16", 5e-3, 5e-3), ("int8", 0.05, 0.1)] {
        let dir = tempfile::tempdir().unwrap();
        convert(&python, precision, dir.path());
        let engine = Engine::load(dir.path(), EngineOptions::default()).unwrap();
        assert_eq!(engine.manifest().precision, precision);
        // `decode` validates every set: finite values, unit rotations, opacities in [0, 1].
        let sets = decode(&engine);
        for (got, want) in sets.iter().zip(&exact) {
            let position = max_relative_position_difference(got.positions(), want.positions());
            let colour = max_difference(got.colors(), want.colors());
            assert!(
                position < bound,
                "{precision}: position differs by {position} of its distance"
            );
            assert!(
                colour < colour_bound,
                "{precision}: colour differs by {colour}"
            );
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
        message.contains("computes in int8") && message.contains("c4g.package.precision"),
        "{message}"
    );
}
