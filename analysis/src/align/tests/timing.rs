//! Time per alignment, printed with the machine (an `--ignored` test; numbers go in the issue
//! notes, never into an assertion):
//!
//!     cargo test --release -p c4g-renderer --lib align::tests::timing -- --ignored --nocapture
//!
//! The cases of issue #17: 512 Gaussians at 64² and 2048 at 224² (C4G's count and input size),
//! each from the tests' perturbation (3°, 5% of the depth), pose only and with the focal length,
//! on rayon's global pool (`RAYON_NUM_THREADS` sets its size). Each case prints its accuracy too.

use std::time::Instant;

use glam::Vec3;

use super::alignment::{perturbation, pose_error, target};
use super::scenes::{camera, oblique, slab};
use crate::align::{AlignOptions, CameraAdjustment, align_camera, camera_jacobian};
use c4g_renderer::{CpuRasterizer, Rasterizer};

fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|s| s.trim().to_owned())
        })
        .unwrap_or_else(|| "unknown CPU".to_owned());
    format!("{cpu}, {} rayon threads", rayon::current_num_threads())
}

#[test]
#[ignore = "a benchmark: run with --release --ignored --nocapture"]
fn time_per_alignment() {
    eprintln!("{}", machine());
    for (size, count, scale) in [(64u32, 512usize, (0.03, 0.15)), (224, 2048, (0.015, 0.08))] {
        let set = slab(21, count, (2.0, 6.0), scale);
        let truth = camera(size, size, oblique());
        let render_options = AlignOptions::default().render;
        let best_of = |f: &dyn Fn()| {
            (0..10)
                .map(|_| {
                    let clock = Instant::now();
                    f();
                    clock.elapsed().as_secs_f64()
                })
                .fold(f64::INFINITY, f64::min)
        };
        let with_jacobian = best_of(&|| {
            let _ = camera_jacobian(&set, &truth, &CameraAdjustment::IDENTITY, &render_options);
        });
        let forward = best_of(&|| {
            let _ = CpuRasterizer::new().render(&set, &truth, &render_options);
        });
        eprintln!(
            "{size}x{size}, {count} Gaussians: one render with its camera Jacobian {:.2} ms \
             (the f32 forward render alone: {:.2} ms)",
            with_jacobian * 1e3,
            forward * 1e3
        );
        for refine_focal in [false, true] {
            let log_focal = if refine_focal { 0.05f64.ln_1p() } else { 0.0 };
            let start = perturbation(log_focal)
                .apply(&truth)
                .unwrap_or_else(|e| panic!("{e}"));
            let options = AlignOptions {
                refine_focal,
                ..AlignOptions::default()
            };
            let frame = target(&set, &truth, &options.render);
            let runs = if size <= 64 { 10 } else { 3 };
            let mut best = f64::INFINITY;
            let mut last = None;
            for _ in 0..runs {
                let clock = Instant::now();
                let alignment =
                    align_camera(&set, &frame, &start, &options).unwrap_or_else(|e| panic!("{e}"));
                best = best.min(clock.elapsed().as_secs_f64());
                last = Some(alignment);
            }
            let Some(a) = last else { continue };
            let (rotation, centre) = pose_error(&a.camera, &truth);
            eprintln!(
                "{size}x{size}, {count} Gaussians, focal {refine_focal}: best of {runs} \
                 {:.1} ms; {} iterations, rotation error {rotation:.2e}°, centre error \
                 {centre:.2e}, focal ratio {:.6}, confidence {:.3}",
                best * 1e3,
                a.iterations,
                a.camera.intrinsics().fx / truth.intrinsics().fx,
                a.confidence,
            );
        }
    }
}

/// How often alignment finds the camera from farther away: 8 scenes and perturbation axes per
/// case, "recovered" meaning the tests' bounds (0.05°, 0.005 scene units).
#[test]
#[ignore = "a benchmark: run with --release --ignored --nocapture"]
fn recovery_rate_by_perturbation() {
    eprintln!("{}", machine());
    for (size, count, scale) in [(64u32, 512usize, (0.03, 0.15)), (224, 2048, (0.015, 0.08))] {
        for (degrees, fraction) in [(3.0f64, 0.05f64), (6.0, 0.1), (10.0, 0.15)] {
            let (mut recovered, mut iterations) = (0, 0);
            let clock = Instant::now();
            for seed in 0..8u64 {
                let set = slab(100 + seed, count, (2.0, 6.0), scale);
                let truth = camera(size, size, oblique());
                let s = seed as f32;
                let axis = Vec3::new(0.6 - 0.2 * s, -0.7 + 0.15 * s, 0.4)
                    .normalize()
                    .as_dvec3()
                    * degrees.to_radians();
                let shift = Vec3::new(-0.5 + 0.1 * s, 0.3, 0.8 - 0.2 * s)
                    .normalize()
                    .as_dvec3()
                    * (4.0 * fraction);
                let start =
                    CameraAdjustment::exp([axis.x, axis.y, axis.z, shift.x, shift.y, shift.z, 0.0])
                        .apply(&truth)
                        .unwrap_or_else(|e| panic!("{e}"));
                let options = AlignOptions::default();
                let frame = target(&set, &truth, &options.render);
                let a =
                    align_camera(&set, &frame, &start, &options).unwrap_or_else(|e| panic!("{e}"));
                let (rotation, centre) = pose_error(&a.camera, &truth);
                recovered += usize::from(rotation < 0.05 && centre < 0.005);
                iterations += a.iterations;
                eprintln!(
                    "  {size}², {degrees}°, {fraction}: seed {seed}: rotation error \
                     {rotation:.3}°, centre error {centre:.4}, confidence {:.3}",
                    a.confidence
                );
            }
            eprintln!(
                "{size}x{size}, {count} Gaussians, {degrees}° and {:.0}% of the depth: \
                 {recovered}/8 recovered, {:.0} iterations and {:.0} ms per alignment",
                fraction * 100.0,
                iterations as f64 / 8.0,
                clock.elapsed().as_secs_f64() * 1e3 / 8.0
            );
        }
    }
}
