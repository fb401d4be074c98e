//! C4G's refinement layout: the Rust pipeline on the `wan-vace-tiny-c4g` package against the
//! PyTorch reference of that layout (`c4g/wan/c4g_layout.py`, diffusers' modules with the same
//! random weights), stage by stage.
//!
//! Tolerances are those of the VACE parity test (`parity.rs`), for the same reason: the graphs
//! compute RoPE from f32 tables where the reference uses f64 ones, and run fused attention, so
//! they differ by float rounding only (absolute; the values are O(1)):
//! - one-frame encoder, positioned transformer on random inputs, control tensor, first
//!   velocity, final latents after 3 guided Euler steps: 1e-4
//! - decoded frames in [0, 1]: 1e-3
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::ops::ControlFlow;
use std::sync::OnceLock;

use c4g_refiner::{
    Keyframe, Layout, Pipeline, PipelineOptions, RefineRequest, RefinerError, Sampler, Schedule,
};
use common::*;

const ATOL: f32 = 1e-4;
const FRAMES_ATOL: f32 = 1e-3;

fn pipeline() -> &'static Pipeline {
    static P: OnceLock<Pipeline> = OnceLock::new();
    P.get_or_init(|| Pipeline::load(c4g_fixture_dir(), &PipelineOptions::default()).unwrap())
}

fn npz(name: &str) -> Npz {
    Npz::open_in(&c4g_fixture_dir(), name)
}

/// `[N, H, W, 3]` → N frames `[H, W, 3]`.
fn frames(npz: &mut Npz, name: &str) -> Vec<Vec<f32>> {
    let n = npz.array(name).shape()[0];
    let flat = npz.vec(name);
    flat.chunks(flat.len() / n).map(<[f32]>::to_vec).collect()
}

/// The reference run's inputs as a request in C4G's layout, with its sampler settings.
fn request(npz: &mut Npz) -> RefineRequest {
    let Layout::C4g(layout) = &pipeline().manifest().layout else {
        panic!("the fixture is not in C4G's layout")
    };
    let keyframes = frames(npz, "keyframes")
        .into_iter()
        .zip(npz.ints("keyframe_indices"))
        .map(|(frame, source_index)| Keyframe {
            frame,
            source_index,
        })
        .collect();
    let mut r = RefineRequest::keyframed(
        layout,
        keyframes,
        frames(npz, "rendered"),
        npz.vec("prompt_embeds"),
    );
    assert_eq!(
        (r.sampler, r.steps, r.shift, r.guidance),
        (Sampler::DiffSynthEuler, 50, 5.0, 5.0),
        "the layout's defaults are the public code's"
    );
    r.negative_embeddings = Some(npz.vec("negative_prompt_embeds"));
    r.steps = npz.int("steps") as usize;
    r.shift = f64::from(npz.scalar("shift"));
    r.guidance = npz.scalar("guidance_scale");
    r.initial_noise = Some(npz.vec("noise"));
    r
}

fn positions(npz: &mut Npz) -> Vec<i64> {
    npz.ints("positions")
}

#[test]
fn frame_encoder_matches_pytorch() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = npz("vae_frame.npz");
    let latents = pipeline().vae_encode_frame(&npz.vec("frame")).unwrap();
    assert_close(
        &latents,
        &npz.vec("latents_mode"),
        ATOL,
        0.0,
        "frame encoder",
    );
}

#[test]
fn positioned_transformer_matches_pytorch() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = npz("transformer_positions.npz");
    let positions = positions(&mut npz);
    assert_eq!(positions, vec![500, 503, 509, 0, 1]);
    let (latents, text) = (npz.vec("latents"), npz.vec("text_embeddings"));
    let (control, scales) = (npz.vec("control"), npz.vec("control_scale"));
    let timestep = npz.scalar("timestep");
    let run = |positions: &[i64]| {
        pipeline()
            .velocity_at(&latents, timestep, &text, &control, &scales, positions)
            .unwrap()
    };
    let v = run(&positions);
    assert_close(&v, &npz.vec("velocity"), ATOL, 0.0, "positioned velocity");
    // The positions reach the graph: VACE's 0..F' give another velocity.
    let (diff, _) = max_abs_diff(&run(&[0, 1, 2, 3, 4]), &v);
    assert!(diff > 1e-2, "positions made no difference ({diff})");
}

#[test]
fn control_tensor_and_first_velocity_match_the_reference() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = npz("pipeline_c4g.npz");
    let r = request(&mut npz);
    let control = pipeline().keyframe_control(&r.keyframes, &r.video).unwrap();
    assert_close(&control, &npz.vec("control"), ATOL, 0.0, "control tensor");
    let scales = vec![1.0; pipeline().manifest().vace_layers.len()];
    let v = pipeline()
        .velocity_at(
            &npz.vec("noise"),
            npz.vec("timesteps")[0],
            &r.text_embeddings,
            &control,
            &scales,
            &positions(&mut npz),
        )
        .unwrap();
    assert_close(&v, &npz.vec("velocity_first"), ATOL, 0.0, "first velocity");
}

#[test]
fn the_schedule_is_diffsynths() {
    let mut npz = npz("pipeline_c4g.npz");
    let steps = npz.int("steps") as usize;
    let s = Schedule::for_sampler(Sampler::DiffSynthEuler, steps, 5.0).unwrap();
    assert_close(s.sigmas(), &npz.vec("sigmas"), 1e-7, 0.0, "sigmas");
    assert_close(s.timesteps(), &npz.vec("timesteps"), 1e-4, 0.0, "timesteps");
}

#[test]
fn a_whole_run_matches_the_reference_and_returns_the_rendered_frames_only() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = npz("pipeline_c4g.npz");
    let r = request(&mut npz);
    let mut reports = Vec::new();
    let out = pipeline()
        .refine(&r, &mut |done, total| {
            reports.push((done, total));
            ControlFlow::Continue(())
        })
        .unwrap();
    assert_eq!(reports, vec![(0, 3), (1, 3), (2, 3), (3, 3)]);
    assert_close(
        &out.latents,
        &npz.vec("latents_final"),
        ATOL,
        0.0,
        "final latents",
    );
    assert_eq!(out.frames.len(), r.video.len(), "padding is dropped");
    assert_close(
        &out.frames.concat(),
        &npz.vec("frames_out"),
        FRAMES_ATOL,
        0.0,
        "frames",
    );
}

#[test]
fn requests_that_do_not_fit_the_layout_are_refused_with_reasons() {
    if skip_reason().is_some() {
        return;
    }
    let mut npz = npz("pipeline_c4g.npz");
    let base = request(&mut npz);
    let refuse = |r: RefineRequest, needle: &str| {
        let err = pipeline()
            .refine(&r, &mut |_, _| ControlFlow::Continue(()))
            .unwrap_err();
        assert!(matches!(err, RefinerError::InvalidRequest(_)), "{err}");
        assert!(err.to_string().contains(needle), "{err}");
    };
    let mut r = base.clone();
    r.keyframes.pop();
    refuse(r, "exactly 3");
    let mut r = base.clone();
    r.video = vec![r.video[0].clone(); 6];
    r.mask = c4g_refiner::Mask::Frames(vec![true; 6]);
    refuse(r, "1 to 5");
    let mut r = base.clone();
    r.keyframes[2].source_index = 600;
    refuse(r, "keyframe 2");
    let mut r = base.clone();
    r.mask = c4g_refiner::Mask::Frames(vec![false, true, true, true]);
    refuse(r, "every rendered frame");
    // The VACE package takes no keyframes.
    let vace = Pipeline::load(fixture_dir(), &PipelineOptions::default()).unwrap();
    let mut r = base;
    r.video = vec![r.video[0].clone(); 9];
    r.mask = c4g_refiner::Mask::Frames(vec![true; 9]);
    r.text_embeddings = vec![0.0; vace.manifest().text_len()];
    r.negative_embeddings = Some(r.text_embeddings.clone());
    r.initial_noise = None;
    let err = vace
        .refine(&r, &mut |_, _| ControlFlow::Continue(()))
        .unwrap_err();
    assert!(err.to_string().contains("VACE's"), "{err}");
}
