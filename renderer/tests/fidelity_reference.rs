//! PSNR and SSIM against the float64 NumPy reference (`models/python/c4g/raster/metrics.py`,
//! fixture `models/fixtures/metrics/cases.safetensors`): within 1e-9 relative, both compute in
//! f64 from the same f32 images.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;

use c4g_renderer::fidelity::{psnr, ssim};
use safetensors::SafeTensors;

#[test]
fn psnr_and_ssim_match_the_reference_with_and_without_a_mask() {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../models/fixtures/metrics/cases.safetensors");
    let bytes = std::fs::read(path).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let f32s = |k: &str| -> Vec<f32> {
        st.tensor(k)
            .unwrap()
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect()
    };
    let f64_of = |k: &str| f64::from_le_bytes(st.tensor(k).unwrap().data().try_into().unwrap());
    let shape = st.tensor("a").unwrap().shape().to_vec();
    let (h, w) = (shape[0] as u32, shape[1] as u32);
    let (a, b) = (f32s("a"), f32s("b"));
    let mask: Vec<bool> = st
        .tensor("mask")
        .unwrap()
        .data()
        .iter()
        .map(|v| *v != 0)
        .collect();
    let close =
        |got: f64, want: f64| assert!((got - want).abs() <= 1e-9 * want.abs(), "{got} vs {want}");
    close(psnr(&a, &b, w, h, None).unwrap(), f64_of("psnr"));
    close(
        psnr(&a, &b, w, h, Some(&mask)).unwrap(),
        f64_of("psnr_masked"),
    );
    close(ssim(&a, &b, w, h, None).unwrap(), f64_of("ssim"));
    close(
        ssim(&a, &b, w, h, Some(&mask)).unwrap(),
        f64_of("ssim_masked"),
    );
}
