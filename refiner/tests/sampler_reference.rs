//! The samplers against diffusers (no ONNX Runtime needed).
//!
//! - `reference/sampler.json`: the sigmas and timesteps of diffusers 0.42's
//!   `UniPCMultistepScheduler` (flow sigmas) and `FlowMatchEulerDiscreteScheduler` for
//!   (4 steps, shift 5) and (30 steps, shift 3). Sigmas within 1e-7 (f32 rounding), timesteps exact
//!   (UniPC's are integers).
//! - `reference/pipeline_{unipc,euler}.npz`: the latents entering each step and the transformer's two
//!   velocities at each step of a real WanVACEPipeline run. Replaying the guided velocities through
//!   our solver must give the next step's latents and the final latents (1e-5 absolute; they are
//!   O(1)): this checks UniPC's predictor, corrector and order schedule without the model.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_refiner::{Sampler, Schedule, Solver};
use common::*;
use serde_json::Value;

fn floats(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

#[test]
fn schedules_match_diffusers() {
    if fixture_skip_reason().is_some() {
        return;
    }
    let text = std::fs::read_to_string(reference_dir().join("sampler.json")).unwrap();
    let json: Value = serde_json::from_str(&text).unwrap();
    for case in json["cases"].as_array().unwrap() {
        let steps = case["steps"].as_u64().unwrap() as usize;
        let shift = case["shift"].as_f64().unwrap();
        for (name, schedule) in [
            ("unipc", Schedule::unipc(steps, shift).unwrap()),
            (
                "flow_match_euler",
                Schedule::flow_match_euler(steps, shift).unwrap(),
            ),
        ] {
            let what = format!("{name} steps {steps} shift {shift}");
            let sigmas = floats(&case[name]["sigmas"]);
            let timesteps = floats(&case[name]["timesteps"]);
            assert_eq!(schedule.sigmas().len(), sigmas.len(), "{what}");
            for (got, want) in schedule.sigmas().iter().zip(&sigmas) {
                assert!(
                    (f64::from(*got) - want).abs() <= 1e-7,
                    "{what}: sigma {got} vs {want}"
                );
            }
            for (got, want) in schedule.timesteps().iter().zip(&timesteps) {
                assert!(
                    (f64::from(*got) - want).abs() <= 1e-4,
                    "{what}: timestep {got} vs {want}"
                );
            }
        }
    }
    let wan = &json["wan_original_test_vector"];
    let s = Schedule::wan(4, 5.0).unwrap();
    for (got, want) in s.sigmas().iter().zip(floats(&wan["sigmas"])) {
        assert!((f64::from(*got) - want).abs() < 1e-6);
    }
    assert_eq!(
        s.timesteps()
            .iter()
            .map(|&t| f64::from(t))
            .collect::<Vec<_>>(),
        floats(&wan["timesteps"])
    );
}

/// Feeds the reference run's guided velocities through our solver, step by step.
fn replay(archive: &str, sampler: Sampler) {
    let mut npz = Npz::open(archive);
    let steps = npz.array("step_latents").shape()[0];
    let shift = f64::from(npz.scalar("shift"));
    let g = npz.scalar("guidance_scale");
    let schedule = Schedule::for_sampler(sampler, steps, shift).unwrap();
    assert_close(
        schedule.sigmas(),
        &npz.vec("sigmas"),
        0.0,
        0.0,
        &format!("{archive} sigmas"),
    );
    assert_close(
        schedule.timesteps(),
        &npz.vec("timesteps"),
        0.0,
        0.0,
        &format!("{archive} timesteps"),
    );
    let mut solver = Solver::new(sampler, schedule);
    let mut x = npz.vec("noise");
    for i in 0..steps {
        let entering = npz.row("step_latents", i);
        assert_close(
            &x,
            &entering,
            1e-5,
            0.0,
            &format!("{archive} latents entering step {i}"),
        );
        let cond = npz.row("step_velocity_cond", i);
        let uncond = npz.row("step_velocity_uncond", i);
        let v: Vec<f32> = uncond
            .iter()
            .zip(&cond)
            .map(|(&u, &c)| u + g * (c - u))
            .collect();
        // Step from the reference's own latents, so each step is checked on its own.
        x = solver.step(&v, &entering).unwrap();
    }
    assert_close(
        &x,
        &npz.vec("latents_final"),
        1e-5,
        0.0,
        &format!("{archive} final latents"),
    );
}

#[test]
fn unipc_replays_the_reference_run() {
    if fixture_skip_reason().is_some() {
        return;
    }
    replay("pipeline_unipc.npz", Sampler::UniPc);
    replay("pipeline_unipc_lora.npz", Sampler::UniPc);
}

#[test]
fn euler_replays_the_reference_run() {
    if fixture_skip_reason().is_some() {
        return;
    }
    replay("pipeline_euler.npz", Sampler::Euler);
}
