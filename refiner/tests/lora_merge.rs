//! The LoRA merge on the fixture's transformer weights (no ONNX Runtime needed).
//!
//! - Both fixture files (PEFT `lora/peft`, Wan-named `lora/wan`) place every module exactly where
//!   `lora/name_map.json` (written by the export, checked there against diffusers) says.
//! - Merged weights equal `W + scale·(alpha/r)·B·A` computed independently in f64 from the raw
//!   safetensors, within 1e-6 of the weight's magnitude; PEFT and Wan files give bit-identical
//!   merged weights; scale 0 merges nothing.
//! - A key that cannot be placed, or whose shape does not fit, is an error naming the key.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use c4g_refiner::lora::merge::{initializer_name, merged_weights};
use c4g_refiner::lora::names::to_diffusers;
use c4g_refiner::onnx::OnnxWeights;
use c4g_refiner::{Lora, RefinerError};
use common::*;
use safetensors::{Dtype, SafeTensors};
use serde_json::Value;

fn peft() -> PathBuf {
    fixture_dir().join("lora/peft/adapter_model.safetensors")
}

fn wan() -> PathBuf {
    fixture_dir().join("lora/wan/lora.safetensors")
}

fn weights() -> OnnxWeights {
    OnnxWeights::open(&fixture_dir().join("transformer.onnx")).unwrap()
}

fn name_map() -> Value {
    let text = std::fs::read_to_string(fixture_dir().join("lora/name_map.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

#[test]
fn both_files_place_every_module_where_the_name_map_says() {
    if fixture_skip_reason().is_some() {
        return;
    }
    let map = name_map();
    let w = weights();
    let expected: BTreeMap<String, String> = map["modules"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| {
            let wan = m["wan"].as_str().unwrap();
            let diffusers = m["diffusers"].as_str().unwrap();
            let init = m["onnx_initializer"].as_str().unwrap();
            assert_eq!(to_diffusers(wan), diffusers, "Wan name {wan}");
            assert_eq!(
                to_diffusers(diffusers),
                diffusers,
                "diffusers name {diffusers}"
            );
            let shape: Vec<usize> = m["shape"]
                .as_array()
                .unwrap()
                .iter()
                .map(|d| d.as_u64().unwrap() as usize)
                .collect();
            assert_eq!(w.get(init).unwrap().dims(), shape.as_slice(), "{init}");
            (diffusers.to_owned(), init.to_owned())
        })
        .collect();
    for file in [peft(), wan()] {
        let lora = Lora::load(&file).unwrap();
        let placed: BTreeMap<String, String> = lora
            .modules()
            .iter()
            .map(|m| (m.module.clone(), initializer_name(m)))
            .collect();
        assert_eq!(placed, expected, "{}", file.display());
        let scale = map["scale"].as_f64().unwrap() as f32;
        assert!(
            lora.modules().iter().all(|m| m.scale == scale),
            "{}",
            file.display()
        );
    }
}

/// `name` of `file` as f64, with its shape.
fn raw_tensor(file: &Path, name: &str) -> (Vec<usize>, Vec<f64>) {
    let bytes = std::fs::read(file).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let t = st.tensor(name).unwrap();
    assert_eq!(t.dtype(), Dtype::F32);
    let values = t
        .data()
        .chunks_exact(4)
        .map(|b| f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])))
        .collect();
    (t.shape().to_vec(), values)
}

#[test]
fn merged_weights_equal_w_plus_scaled_b_times_a_in_f64() {
    if fixture_skip_reason().is_some() {
        return;
    }
    let w = weights();
    let user_scale = 0.7f32;
    let file_scale = name_map()["scale"].as_f64().unwrap();
    let merged = merged_weights(&Lora::load(&peft()).unwrap(), &w, user_scale).unwrap();
    assert_eq!(
        merged.len(),
        name_map()["modules"].as_array().unwrap().len()
    );
    let mut worst = 0.0f64;
    for m in &merged {
        let module = m.name.strip_suffix(".weight").unwrap();
        let (a_shape, a) = raw_tensor(&peft(), &format!("transformer.{module}.lora_A.weight"));
        let (b_shape, b) = raw_tensor(&peft(), &format!("transformer.{module}.lora_B.weight"));
        let (r, cols, rows) = (a_shape[0], a_shape[1], b_shape[0]);
        let base = w.read_f32(w.get(&m.name).unwrap()).unwrap();
        let got = m.values.to_f32();
        let magnitude = base.iter().map(|v| f64::from(v.abs())).fold(0.0, f64::max);
        for o in 0..rows {
            for i in 0..cols {
                let delta: f64 = (0..r).map(|k| b[o * r + k] * a[k * cols + i]).sum();
                let expected =
                    f64::from(base[o * cols + i]) + f64::from(user_scale) * file_scale * delta;
                let err = (f64::from(got[o * cols + i]) - expected).abs() / magnitude;
                worst = worst.max(err);
            }
        }
    }
    eprintln!("worst merged-weight error relative to the weight's magnitude: {worst:.2e}");
    assert!(worst < 1e-6, "{worst:e}");
}

#[test]
fn peft_and_wan_files_merge_to_identical_weights() {
    if fixture_skip_reason().is_some() {
        return;
    }
    let w = weights();
    let from_peft = merged_weights(&Lora::load(&peft()).unwrap(), &w, 1.0).unwrap();
    let from_wan = merged_weights(&Lora::load(&wan()).unwrap(), &w, 1.0).unwrap();
    let key = |v: &[c4g_refiner::lora::merge::MergedWeight]| {
        let mut v = v.to_vec();
        v.sort_by(|a, b| a.name.cmp(&b.name));
        v
    };
    assert_eq!(key(&from_peft), key(&from_wan));
}

#[test]
fn scale_zero_merges_nothing_but_still_checks_every_key() {
    if fixture_skip_reason().is_some() {
        return;
    }
    let w = weights();
    assert!(
        merged_weights(&Lora::load(&peft()).unwrap(), &w, 0.0)
            .unwrap()
            .is_empty()
    );
    let dir = tempfile::tempdir().unwrap();
    let bad = with_extra_key(
        &wan(),
        dir.path(),
        "diffusion_model.blocks.0.self_attn.qq",
        &[4, 16],
        &[16, 4],
    );
    let err = merged_weights(&Lora::load(&bad).unwrap(), &w, 0.0).unwrap_err();
    assert!(err.to_string().contains("blocks.0.self_attn.qq"), "{err}");
}

/// A copy of the Wan-named `file` with one more down / up pair for `module`.
fn with_extra_key(file: &Path, dir: &Path, module: &str, down: &[usize], up: &[usize]) -> PathBuf {
    let bytes = std::fs::read(file).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let mut tensors: Vec<(String, Vec<usize>, Vec<u8>)> = st
        .tensors()
        .into_iter()
        .map(|(k, v)| (k, v.shape().to_vec(), v.data().to_vec()))
        .collect();
    for (suffix, shape) in [("lora_down.weight", down), ("lora_up.weight", up)] {
        let n: usize = shape.iter().product();
        tensors.push((
            format!("{module}.{suffix}"),
            shape.to_vec(),
            vec![0u8; 4 * n],
        ));
    }
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = tensors
        .iter()
        .map(|(k, s, d)| {
            (
                k.clone(),
                safetensors::tensor::TensorView::new(Dtype::F32, s.clone(), d).unwrap(),
            )
        })
        .collect();
    let path = dir.join("lora.safetensors");
    std::fs::write(&path, safetensors::serialize(views, None).unwrap()).unwrap();
    path
}

#[test]
fn a_key_that_cannot_be_placed_or_does_not_fit_is_an_error_naming_it() {
    if fixture_skip_reason().is_some() {
        return;
    }
    let w = weights();
    let dir = tempfile::tempdir().unwrap();
    // No such module in the transformer.
    let bad = with_extra_key(
        &wan(),
        dir.path(),
        "diffusion_model.blocks.9.self_attn.q",
        &[4, 32],
        &[32, 4],
    );
    let err = merged_weights(&Lora::load(&bad).unwrap(), &w, 1.0).unwrap_err();
    assert!(matches!(err, RefinerError::Lora { .. }), "{err}");
    assert!(err.to_string().contains("blocks.9.self_attn.q"), "{err}");
    assert!(
        err.to_string().contains("blocks.9.attn1.to_q.weight"),
        "{err}"
    );
    // A real module (not adapted by the fixture LoRA), with the wrong input width.
    let bad = with_extra_key(
        &wan(),
        dir.path(),
        "diffusion_model.text_embedding.0",
        &[4, 31],
        &[32, 4],
    );
    let err = merged_weights(&Lora::load(&bad).unwrap(), &w, 1.0).unwrap_err();
    assert!(err.to_string().contains("text_embedding.0"), "{err}");
    assert!(err.to_string().contains("does not fit"), "{err}");
}
