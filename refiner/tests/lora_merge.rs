//! The LoRA merge on the fixture's transformer weights (no ONNX Runtime needed).
//!
//! - Both fixture files (PEFT `lora/peft`, Wan-named `lora/wan`) place every module exactly where
//!   `lora/name_map.json` (written by the export, checked there against diffusers) says.
//! - Merged weights equal `W + scale·(alpha/r)·B·A` computed independently in f64 from the raw
//!   safetensors, within 1e-6 of the weight's magnitude; PEFT and Wan files give bit-identical
//!   merged weights; scale 0 merges nothing.
//! - A key that cannot be placed, or whose shape does not fit, is an error naming the key.
//! - C4G's published format (DiffSynth-Studio's PEFT keys on the VACE branch, no alpha) merges
//!   onto exactly the VACE blocks' attention and FFN linears.
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

/// C4G's published LoRA, as its DiffSynth-Studio fork saves it: PEFT's adapter name in the keys
/// (`vace_blocks.N.self_attn.q.lora_A.default.weight`, `lora_B.default.weight`), the `pipe.vace.`
/// prefix removed, no alpha tensor and no adapter_config.json (alpha = rank: scale 1), on the VACE
/// branch's self-attention, cross-attention and FFN linears (`WAN_VACE.md`, "C4G's own refinement
/// pipeline"). Built here in exactly that format with random factors over every VACE block of the
/// fixture: each targeted module merges to `W + B·A` (f64, scale 1) and no other weight is touched.
#[test]
fn a_diffsynth_lora_on_the_vace_branch_merges_onto_exactly_its_modules() {
    if fixture_skip_reason().is_some() {
        return;
    }
    use rand_chacha::rand_core::{RngCore, SeedableRng};
    let w = weights();
    let blocks: std::collections::BTreeSet<usize> = w
        .names()
        .into_iter()
        .filter_map(|n| {
            n.strip_prefix("vace_blocks.")?
                .split('.')
                .next()?
                .parse()
                .ok()
        })
        .collect();
    assert!(!blocks.is_empty(), "the fixture has no VACE blocks");
    let (rank, mut rng) = (4, rand_chacha::ChaCha8Rng::seed_from_u64(19));
    let mut uniform = move || (rng.next_u32() as f32 / u32::MAX as f32 - 0.5) * 0.2;
    let mut tensors: Vec<(String, Vec<usize>, Vec<f32>)> = Vec::new();
    let mut expected: BTreeMap<String, (Vec<f32>, Vec<f32>, usize, usize)> = BTreeMap::new();
    for block in &blocks {
        for (wan, diffusers) in [
            ("self_attn.q", "attn1.to_q"),
            ("self_attn.k", "attn1.to_k"),
            ("self_attn.v", "attn1.to_v"),
            ("self_attn.o", "attn1.to_out.0"),
            ("cross_attn.q", "attn2.to_q"),
            ("cross_attn.k", "attn2.to_k"),
            ("cross_attn.v", "attn2.to_v"),
            ("cross_attn.o", "attn2.to_out.0"),
            ("ffn.0", "ffn.net.0.proj"),
            ("ffn.2", "ffn.net.2"),
        ] {
            let initializer = format!("vace_blocks.{block}.{diffusers}.weight");
            let dims = w.get(&initializer).unwrap().dims().to_vec();
            let (rows, cols) = (dims[0], dims[1]);
            let a: Vec<f32> = (0..rank * cols).map(|_| uniform()).collect();
            let b: Vec<f32> = (0..rows * rank).map(|_| uniform()).collect();
            let key = format!("vace_blocks.{block}.{wan}");
            tensors.push((
                format!("{key}.lora_A.default.weight"),
                vec![rank, cols],
                a.clone(),
            ));
            tensors.push((
                format!("{key}.lora_B.default.weight"),
                vec![rows, rank],
                b.clone(),
            ));
            expected.insert(initializer, (a, b, rows, cols));
        }
    }
    let bytes: Vec<Vec<u8>> = tensors
        .iter()
        .map(|(_, _, v)| v.iter().flat_map(|x| x.to_le_bytes()).collect())
        .collect();
    let views: Vec<(String, safetensors::tensor::TensorView<'_>)> = tensors
        .iter()
        .zip(&bytes)
        .map(|((k, s, _), d)| {
            (
                k.clone(),
                safetensors::tensor::TensorView::new(Dtype::F32, s.clone(), d).unwrap(),
            )
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c4g_vace_lora.safetensors");
    std::fs::write(&path, safetensors::serialize(views, None).unwrap()).unwrap();

    let lora = Lora::load(&path).unwrap();
    assert!(
        lora.modules().iter().all(|m| m.scale == 1.0),
        "no alpha: scale 1"
    );
    let merged = merged_weights(&lora, &w, 1.0).unwrap();
    let names: Vec<&str> = merged.iter().map(|m| m.name.as_str()).collect();
    let targeted: Vec<&str> = expected.keys().map(String::as_str).collect();
    assert_eq!(
        names, targeted,
        "merged exactly the targeted weights, nothing else"
    );
    let mut worst = 0.0f64;
    for m in &merged {
        let (a, b, rows, cols) = &expected[&m.name];
        let base = w.read_f32(w.get(&m.name).unwrap()).unwrap();
        let got = m.values.to_f32();
        let magnitude = base
            .iter()
            .map(|v| f64::from(v.abs()))
            .fold(1e-12, f64::max);
        for o in 0..*rows {
            for i in 0..*cols {
                let delta: f64 = (0..rank)
                    .map(|k| f64::from(b[o * rank + k]) * f64::from(a[k * cols + i]))
                    .sum();
                let err = (f64::from(got[o * cols + i]) - (f64::from(base[o * cols + i]) + delta))
                    .abs()
                    / magnitude;
                worst = worst.max(err);
            }
        }
    }
    assert!(worst < 1e-6, "{worst:e}");
    assert!(
        merged.iter().all(|m| m.name.starts_with("vace_blocks.")),
        "the main blocks are untouched"
    );
}
