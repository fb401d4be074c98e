//! Numerical parity of the Rust pipeline (ONNX Runtime on the exported graphs) with diffusers'
//! WanVACEPipeline on the same random-weight models (`reference/`, made by `c4g.wan.export --tiny`).
//!
//! The graphs compute RoPE in f32 where diffusers uses f64 tables, and run fused attention, so
//! outputs differ from the reference by float rounding only. Tolerances (absolute; the values
//! are O(1)), with what was measured when they were set in parentheses:
//! - VAE encoder / decoder, transformer on random inputs: 1e-4
//! - control tensor, first velocity: 1e-4
//! - final latents after 4 steps (UniPC, Euler; base and LoRA): 1e-4
//! - decoded frames in [0, 1]: 1e-3
//! - Wan-named and PEFT LoRA files give the same output; LoRA scale 0 is the base model bit for bit.
//! - A transformer with its weights in external data (as every real-size export has) merges the
//!   LoRA the same as one with inline weights, also when only some adapted weights are external.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::collections::BTreeSet;
use std::ops::ControlFlow;
use std::sync::OnceLock;

use c4g_refiner::onnx::OnnxWeights;
use c4g_refiner::{
    LoraSpec, Mask, Pipeline, PipelineOptions, RefineOutput, RefineRequest, RefinerError, Sampler,
};
use common::external::externalize;
use common::*;

const ATOL: f32 = 1e-4;
const FRAMES_ATOL: f32 = 1e-3;

fn base() -> &'static Pipeline {
    static P: OnceLock<Pipeline> = OnceLock::new();
    P.get_or_init(|| Pipeline::load(fixture_dir(), &PipelineOptions::default()).unwrap())
}

fn with_lora(file: &str, scale: f32) -> Pipeline {
    let options = PipelineOptions {
        lora: Some(LoraSpec {
            path: fixture_dir().join(file),
            scale,
        }),
        ..PipelineOptions::default()
    };
    Pipeline::load(fixture_dir(), &options).unwrap()
}

/// `[F, H, W, 3]` → F frames `[H, W, 3]`.
fn frames(flat: &[f32], count: usize) -> Vec<Vec<f32>> {
    let len = flat.len() / count;
    flat.chunks(len).map(<[f32]>::to_vec).collect()
}

/// The reference run's inputs as a request.
fn request(npz: &mut Npz, sampler: Sampler) -> RefineRequest {
    let f = npz.array("video").shape()[0];
    let mask = npz.vec("mask");
    let mut r = RefineRequest::new(
        frames(&npz.vec("video"), f),
        Mask::Pixels(frames(&mask, f)),
        npz.vec("prompt_embeds"),
    );
    r.negative_embeddings = Some(npz.vec("negative_prompt_embeds"));
    r.steps = npz.int("steps") as usize;
    r.shift = f64::from(npz.scalar("shift"));
    r.guidance = npz.scalar("guidance_scale");
    r.control_scale = 1.0;
    r.sampler = sampler;
    r.initial_noise = Some(npz.vec("noise"));
    r
}

fn run(pipeline: &Pipeline, request: &RefineRequest) -> RefineOutput {
    pipeline
        .refine(request, &mut |_, _| ControlFlow::Continue(()))
        .unwrap()
}

fn check_run(pipeline: &Pipeline, archive: &str, sampler: Sampler) -> RefineOutput {
    let mut npz = Npz::open(archive);
    let out = run(pipeline, &request(&mut npz, sampler));
    assert_close(
        &out.latents,
        &npz.vec("latents_final"),
        ATOL,
        0.0,
        &format!("{archive} final latents"),
    );
    let expected = npz.vec("frames_out");
    assert_close(
        &out.frames.concat(),
        &expected,
        FRAMES_ATOL,
        0.0,
        &format!("{archive} frames"),
    );
    out
}

#[test]
fn vae_matches_diffusers() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = Npz::open("vae.npz");
    let latents = base().vae_encode(&npz.vec("video")).unwrap();
    assert_close(&latents, &npz.vec("latents_mode"), ATOL, 0.0, "VAE encoder");
    let video = base().vae_decode(&npz.vec("latents")).unwrap();
    assert_close(&video, &npz.vec("video_decoded"), ATOL, 0.0, "VAE decoder");
}

#[test]
fn transformer_matches_diffusers_with_per_layer_control_scales() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = Npz::open("transformer.npz");
    let v = base()
        .velocity(
            &npz.vec("latents"),
            npz.scalar("timestep"),
            &npz.vec("text_embeddings"),
            &npz.vec("control"),
            &npz.vec("control_scale"),
        )
        .unwrap();
    assert_close(&v, &npz.vec("velocity"), ATOL, 0.0, "transformer velocity");
}

#[test]
fn control_tensor_and_first_velocity_match_diffusers() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = Npz::open("pipeline_unipc.npz");
    let r = request(&mut npz, Sampler::UniPc);
    let control = base().control(&r.video, &r.mask).unwrap();
    let expected = npz.vec("control");
    assert_close(
        &control[..16 * 72],
        &expected[..16 * 72],
        ATOL,
        0.0,
        "control: inactive latents",
    );
    assert_close(
        &control[16 * 72..32 * 72],
        &expected[16 * 72..32 * 72],
        ATOL,
        0.0,
        "control: reactive latents",
    );
    assert_eq!(
        &control[32 * 72..],
        &expected[32 * 72..],
        "control: mask channels"
    );

    let timestep = npz.vec("timesteps")[0];
    let scales = vec![1.0; base().manifest().vace_layers.len()];
    let v = base()
        .velocity(
            &npz.vec("noise"),
            timestep,
            &r.text_embeddings,
            &control,
            &scales,
        )
        .unwrap();
    assert_close(&v, &npz.vec("velocity_first"), ATOL, 0.0, "first velocity");
}

#[test]
fn unipc_refinement_matches_diffusers() {
    if skip_reason().is_some() {
        return;
    }
    check_run(base(), "pipeline_unipc.npz", Sampler::UniPc);
}

#[test]
fn euler_refinement_matches_diffusers() {
    if skip_reason().is_some() {
        return;
    }
    check_run(base(), "pipeline_euler.npz", Sampler::Euler);
}

#[test]
fn lora_refinement_matches_diffusers_for_both_file_conventions() {
    if skip_reason().is_some() {
        return;
    }
    let peft = with_lora("lora/peft/adapter_model.safetensors", 1.0);
    let text = std::fs::read_to_string(fixture_dir().join("lora/name_map.json")).unwrap();
    let map: serde_json::Value = serde_json::from_str(&text).unwrap();
    assert_eq!(
        peft.merged_weight_count(),
        map["modules"].as_array().unwrap().len()
    );
    let from_peft = check_run(&peft, "pipeline_unipc_lora.npz", Sampler::UniPc);
    let wan = with_lora("lora/wan/lora.safetensors", 1.0);
    let from_wan = check_run(&wan, "pipeline_unipc_lora.npz", Sampler::UniPc);
    assert_eq!(
        from_peft, from_wan,
        "PEFT and Wan files must give the same refinement"
    );
    // And the LoRA matters: without it the result is the base run's, far from the LoRA run's.
    let mut npz = Npz::open("pipeline_unipc_lora.npz");
    let plain = run(base(), &request(&mut npz, Sampler::UniPc));
    let (diff, _) = max_abs_diff(&plain.latents, &from_peft.latents);
    assert!(
        diff > 100.0 * ATOL,
        "the LoRA changed the latents by only {diff:e}"
    );
}

#[test]
fn lora_scale_zero_is_the_base_model_bit_for_bit() {
    if skip_reason().is_some() {
        return;
    }
    let zero = with_lora("lora/peft/adapter_model.safetensors", 0.0);
    assert_eq!(zero.merged_weight_count(), 0);
    let mut npz = Npz::open("pipeline_unipc.npz");
    let r = request(&mut npz, Sampler::UniPc);
    assert_eq!(run(&zero, &r), run(base(), &r));
}

#[test]
fn guidance_one_runs_the_conditional_branch_only() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = Npz::open("pipeline_unipc.npz");
    let mut r = request(&mut npz, Sampler::UniPc);
    r.guidance = 1.0;
    let with_negative = run(base(), &r);
    r.negative_embeddings = None;
    assert_eq!(run(base(), &r), with_negative);
}

#[test]
fn seeded_runs_repeat_and_differ_by_seed() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = Npz::open("pipeline_unipc.npz");
    let mut r = request(&mut npz, Sampler::Euler);
    r.initial_noise = None;
    r.steps = 2;
    r.seed = 11;
    let a = run(base(), &r);
    assert_eq!(run(base(), &r), a);
    r.seed = 12;
    assert_ne!(run(base(), &r).latents, a.latents);
    assert!(a.frames.iter().flatten().all(|v| (0.0..=1.0).contains(v)));
}

#[test]
fn progress_reports_every_step_and_break_cancels() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = Npz::open("pipeline_unipc.npz");
    let r = request(&mut npz, Sampler::UniPc);
    let mut seen = Vec::new();
    base()
        .refine(&r, &mut |done, total| {
            seen.push((done, total));
            ControlFlow::Continue(())
        })
        .unwrap();
    assert_eq!(seen, vec![(0, 4), (1, 4), (2, 4), (3, 4), (4, 4)]);
    let err = base()
        .refine(&r, &mut |done, _| {
            if done == 2 {
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        })
        .unwrap_err();
    assert!(
        matches!(
            err,
            RefinerError::Cancelled {
                completed: 2,
                total: 4
            }
        ),
        "{err}"
    );
}

#[test]
fn requests_that_do_not_fit_the_package_are_refused() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = Npz::open("pipeline_unipc.npz");
    let good = request(&mut npz, Sampler::UniPc);
    let mut cases: Vec<(&str, RefineRequest)> = Vec::new();
    let mut r = good.clone();
    r.video.pop();
    cases.push(("frames", r));
    let mut r = good.clone();
    r.text_embeddings.pop();
    cases.push(("text_embeddings", r));
    let mut r = good.clone();
    r.negative_embeddings = None;
    cases.push(("negative_embeddings", r));
    let mut r = good.clone();
    r.steps = 0;
    cases.push(("steps", r));
    let mut r = good.clone();
    r.initial_noise = Some(vec![0.0; 3]);
    cases.push(("initial_noise", r));
    let mut r = good;
    r.mask = Mask::Frames(vec![true; 2]);
    cases.push(("mask", r));
    for (what, r) in cases {
        let err = base()
            .refine(&r, &mut |_, _| ControlFlow::Continue(()))
            .unwrap_err();
        assert!(
            matches!(err, RefinerError::InvalidRequest(_)),
            "{what}: {err}"
        );
        assert!(err.to_string().contains(what), "{what}: {err}");
    }
}

/// A copy of the fixture package whose transformer keeps the initializers `move_it` picks in
/// external data; also returns the names moved.
fn external_package(
    move_it: &dyn Fn(&str, usize) -> bool,
) -> (tempfile::TempDir, BTreeSet<String>) {
    let dir = tempfile::tempdir().unwrap();
    for f in [
        "refiner.json",
        "vae_encoder.onnx",
        "vae_decoder.onnx",
        "text_encoder.onnx",
        "tokenizer.json",
    ] {
        std::fs::copy(fixture_dir().join(f), dir.path().join(f)).unwrap();
    }
    let moved = externalize(&fixture_dir().join("transformer.onnx"), dir.path(), move_it);
    (dir, moved)
}

fn lora_targets() -> Vec<String> {
    let text = std::fs::read_to_string(fixture_dir().join("lora/name_map.json")).unwrap();
    let map: serde_json::Value = serde_json::from_str(&text).unwrap();
    let mut names: Vec<String> = map["modules"]
        .as_array()
        .unwrap()
        .iter()
        .map(|m| m["onnx_initializer"].as_str().unwrap().to_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn lora_merges_into_external_data_as_into_inline_weights() {
    if skip_reason().is_some() {
        return;
    }
    let targets = lora_targets();
    let every_other: BTreeSet<String> = targets.iter().step_by(2).cloned().collect();
    let inline = with_lora("lora/peft/adapter_model.safetensors", 1.0);
    let mut npz = Npz::open("pipeline_unipc_lora.npz");
    let expected = run(&inline, &request(&mut npz, Sampler::UniPc));
    type Selector = Box<dyn Fn(&str, usize) -> bool>;
    let layouts: [(&str, Selector); 2] = [
        (
            "every weight of 256+ values external",
            Box::new(|_: &str, n: usize| n >= 256),
        ),
        (
            "half the adapted weights external",
            Box::new(move |name: &str, _| every_other.contains(name)),
        ),
    ];
    for (what, move_it) in layouts {
        let (dir, moved) = external_package(&*move_it);
        let external: Vec<&String> = targets.iter().filter(|t| moved.contains(*t)).collect();
        assert!(
            !external.is_empty() && moved.len() > 1,
            "{what}: moved {moved:?}"
        );
        let (a, b) = (
            OnnxWeights::open(&fixture_dir().join("transformer.onnx")).unwrap(),
            OnnxWeights::open(&dir.path().join("transformer.onnx")).unwrap(),
        );
        for name in &moved {
            assert!(b.get(name).unwrap().is_external(), "{what}: {name}");
            assert_eq!(
                a.read_f32(a.get(name).unwrap()).unwrap(),
                b.read_f32(b.get(name).unwrap()).unwrap()
            );
        }
        let data_files = || {
            let mut files: Vec<(std::path::PathBuf, Vec<u8>)> = std::fs::read_dir(dir.path())
                .unwrap()
                .map(|e| e.unwrap().path())
                .filter(|p| p.extension().is_some_and(|e| e == "data"))
                .map(|p| (p.clone(), std::fs::read(&p).unwrap()))
                .collect();
            files.sort();
            files
        };
        let before = data_files();
        assert!(!before.is_empty(), "{what}: no external data file");
        let scratch = tempfile::tempdir().unwrap();
        let options = PipelineOptions {
            lora: Some(LoraSpec {
                path: fixture_dir().join("lora/peft/adapter_model.safetensors"),
                scale: 1.0,
            }),
            merge_dir: Some(scratch.path().to_path_buf()),
            ..PipelineOptions::default()
        };
        let p = Pipeline::load(dir.path(), &options).unwrap();
        // The merge wrote into a copy of the external data, which is gone once the session
        // exists; the package's own files are as they were.
        assert_eq!(
            std::fs::read_dir(scratch.path()).unwrap().count(),
            0,
            "{what}: the merge's scratch folder was left behind"
        );
        assert!(
            data_files() == before,
            "{what}: the package's external data changed"
        );
        let got = check_run(&p, "pipeline_unipc_lora.npz", Sampler::UniPc);
        let (diff, _) = max_abs_diff(&got.latents, &expected.latents);
        eprintln!(
            "{what}: {} of {} adapted weights external, latents differ from inline by {diff:e}",
            external.len(),
            targets.len()
        );
        assert!(diff <= 1e-6, "{what}: {diff:e}");
        // Without the LoRA the external-data package is the base model.
        let plain = Pipeline::load(dir.path(), &PipelineOptions::default()).unwrap();
        let mut npz = Npz::open("pipeline_unipc.npz");
        assert_eq!(
            run(&plain, &request(&mut npz, Sampler::UniPc)),
            run(base(), &request(&mut npz, Sampler::UniPc))
        );
    }
}
