//! Preprocessing against the reference's own output: one real frame (960x540) centre-cropped
//! and resized to 224x224 by Pillow's Lanczos on 8-bit data (`preprocess.npz`).
//!
//! Measured here (fast_image_resize 6.1, passes run horizontal-then-vertical as Pillow does):
//! max abs difference 1/255, in 696 of 150,528 values (0.46%); every other value is identical.
//! Running fast_image_resize's single fused resize (vertical pass first) instead gives 2/255 in
//! 18,900 values. The residue comes from its 15-bit fixed-point coefficients (Pillow uses 22 bits).
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::fs::File;
use std::path::PathBuf;

use c4g_engine::preprocess::{center_square_crop, crop_and_resize, to_model_input};
use image::RgbImage;
use ndarray::{Array1, Array3};
use ndarray_npy::NpzReader;

/// The bound this test holds the resize to: one 8-bit step.
const MAX_ABS_DIFF: f32 = 1.0 / 255.0;
/// At most this share of values may differ at all.
const MAX_DIFFERING_SHARE: f64 = 0.01;

fn shared_dir() -> PathBuf {
    std::env::var_os("C4G_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared"))
}

#[test]
fn lanczos_resize_matches_pillow_within_one_8_bit_step() {
    let path = shared_dir().join("reference/c4g-official-small/preprocess.npz");
    if !path.is_file() {
        eprintln!("skipped: {} not found (set C4G_SHARED)", path.display());
        return;
    }
    let mut npz = NpzReader::new(File::open(&path).unwrap()).unwrap();
    let input: Array3<u8> = npz.by_name("input_rgb_u8").unwrap();
    let crop_box: Array1<i64> = npz.by_name("crop_box").unwrap();
    let expected: Array3<f32> = npz.by_name("output_rgb").unwrap();

    let (h, w, _) = input.dim();
    let frame = RgbImage::from_raw(w as u32, h as u32, input.iter().copied().collect()).unwrap();
    let b = center_square_crop(frame.width(), frame.height());
    let ours = [b.left, b.top, b.right, b.bottom].map(i64::from);
    assert_eq!(
        crop_box.to_vec(),
        ours.to_vec(),
        "crop box (left, top, right, bottom)"
    );

    let resized = crop_and_resize(&frame, 224, 224).unwrap();
    let values = to_model_input(&resized, [0.0, 1.0]);
    assert_eq!(values.len(), expected.len());
    let diffs: Vec<f32> = values
        .iter()
        .zip(expected.iter())
        .map(|(a, b)| (a - b).abs())
        .collect();
    let max = diffs.iter().copied().fold(0.0f32, f32::max);
    let differing = diffs.iter().filter(|&&d| d > 0.0).count();
    let share = differing as f64 / diffs.len() as f64;
    eprintln!(
        "lanczos vs Pillow: max abs diff {max} ({:.3}/255), {differing} of {} values differ ({:.2}%)",
        max * 255.0,
        diffs.len(),
        share * 100.0
    );
    assert!(max <= MAX_ABS_DIFF + 1e-7, "max abs diff {max} > 1/255");
    assert!(share <= MAX_DIFFERING_SHARE, "{differing} values differ");
}
