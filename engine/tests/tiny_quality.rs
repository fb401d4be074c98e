//! The default model, c4g-tiny, through the Rust path (ONNX Runtime engine + CPU rasterizer) on its
//! committed test clips: the PSNR of every target, at its own camera and at a novel view, must equal
//! what the Python path (PyTorch mirror + fast rasterizer, `python -m c4g.eval.held_out`) measured and
//! wrote into each clip's `clip.json`, within 0.1 dB. Also a floor on quality: the model must beat
//! the mean-colour baseline there, so a broken package cannot pass by matching a broken Python run.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};

use c4g_engine::{ContextFrame, Engine, EngineOptions};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions, fidelity};
use c4g_scene::{Camera, NormalizedIntrinsics};
use glam::Mat4;
use serde_json::Value;

const PSNR_TOLERANCE_DB: f64 = 0.1;

fn tiny_dir() -> PathBuf {
    common::workspace().join("models/c4g-tiny")
}

fn load_rgb(path: &Path) -> image::RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
}

fn to_unit(img: &image::RgbImage) -> Vec<f32> {
    img.as_raw().iter().map(|&v| f32::from(v) / 255.0).collect()
}

fn pose(value: &Value) -> Mat4 {
    let rows: Vec<Vec<f32>> = serde_json::from_value(value.clone()).unwrap();
    let mut cols = [[0.0f32; 4]; 4];
    for (r, row) in rows.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            cols[c][r] = *v;
        }
    }
    Mat4::from_cols_array_2d(&cols)
}

fn render_psnr(set: &c4g_scene::GaussianSet, w2c: Mat4, truth: &image::RgbImage) -> f64 {
    let (w, h) = truth.dimensions();
    let camera =
        Camera::from_world_to_camera_matrix(NormalizedIntrinsics::C4G_DEFAULT.to_pixels(w, h), w2c)
            .unwrap();
    let image = CpuRasterizer::new()
        .render(set, &camera, &RenderOptions::default())
        .unwrap();
    let rgb: Vec<f32> = image.rgb.iter().map(|v| v.clamp(0.0, 1.0)).collect();
    fidelity::psnr(&rgb, &to_unit(truth), w, h, None).unwrap()
}

#[test]
fn test_clips_score_the_python_paths_psnr_through_engine_and_renderer() {
    if std::env::var_os("ORT_DYLIB_PATH").is_none_or(|p| p.is_empty()) {
        assert!(
            std::env::var_os("CI").is_none(),
            "in CI this test must run: ORT_DYLIB_PATH is not set"
        );
        eprintln!("skipped: ORT_DYLIB_PATH is not set");
        return;
    }
    let engine = Engine::load(tiny_dir(), EngineOptions::default()).unwrap();
    let mut clips: Vec<PathBuf> = std::fs::read_dir(tiny_dir().join("test-clips"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.join("clip.json").is_file())
        .collect();
    clips.sort();
    assert!(
        !clips.is_empty(),
        "no test clips in models/c4g-tiny/test-clips"
    );
    for dir in clips {
        let meta: Value =
            serde_json::from_str(&std::fs::read_to_string(dir.join("clip.json")).unwrap()).unwrap();
        let times: Vec<f64> = serde_json::from_value(meta["times"].clone()).unwrap();
        let names: Vec<String> = serde_json::from_value(meta["frames"].clone()).unwrap();
        let frames: Vec<_> = names.iter().map(|n| load_rgb(&dir.join(n))).collect();
        let context: Vec<usize> = serde_json::from_value(meta["context"].clone()).unwrap();
        let targets: Vec<usize> = serde_json::from_value(meta["targets"].clone()).unwrap();
        let inputs: Vec<ContextFrame> = context
            .iter()
            .map(|&i| ContextFrame::new(times[i], engine.preprocess(&frames[i]).unwrap()))
            .collect();
        let encoding = engine.encode(&inputs).unwrap();
        let target_times: Vec<f64> = targets.iter().map(|&i| times[i]).collect();
        let sets = engine.decode(&encoding, &target_times).unwrap();
        for (k, (&frame, set)) in targets.iter().zip(&sets).enumerate() {
            let novel_truth = load_rgb(&dir.join(format!("novel-{k:02}.png")));
            let cases = [
                (
                    "interpolated",
                    pose(&meta["world_to_camera_model"][frame]),
                    &frames[frame],
                ),
                (
                    "novel",
                    pose(&meta["novel_world_to_camera_model"][k]),
                    &novel_truth,
                ),
            ];
            for (kind, w2c, truth) in cases {
                let ours = render_psnr(set, w2c, truth);
                let python = meta["python_psnr"][kind][k].as_f64().unwrap();
                assert!(
                    (ours - python).abs() <= PSNR_TOLERANCE_DB,
                    "{} target {k} ({kind}): Rust path {ours:.3} dB, Python path {python:.3} dB",
                    dir.display()
                );
                // Mean colour of the context frames as the image: the floor a model must clear.
                let mut mean = [0.0f64; 3];
                for &i in &context {
                    for (p, v) in frames[i].as_raw().iter().enumerate() {
                        mean[p % 3] += f64::from(*v) / 255.0;
                    }
                }
                let pixels = (truth.width() * truth.height()) as f64 * context.len() as f64;
                let flat: Vec<f32> = (0..truth.as_raw().len())
                    .map(|p| (mean[p % 3] / pixels) as f32)
                    .collect();
                let baseline =
                    fidelity::psnr(&flat, &to_unit(truth), truth.width(), truth.height(), None)
                        .unwrap();
                assert!(
                    ours > baseline + 3.0,
                    "{} target {k} ({kind}): {ours:.2} dB does not clear the mean colour ({baseline:.2} dB)",
                    dir.display()
                );
            }
        }
    }
}
