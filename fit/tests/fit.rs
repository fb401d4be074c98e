//! The fit as issue 38 specifies it, on a synthetic moving scene: 32 Gaussians (half static, half
//! moving linearly), seen at 48×40 by one fixed camera at 12 times, their truth given as 4
//! keyframe sets (Hermite with Bessel tangents reproduces linear motion, so the truth's `at(t)` is
//! the motion itself). Fits start from the truth perturbed (positions, scales, colours), as a
//! feed-forward answer is near but not at the scene; frames 3, 7 and 11 are held out.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use c4g_fit::{Control, FitOptions, FittedScene, Frame, fit};
use c4g_optim::schedule::LearningRate;
use c4g_optim::{DensifyConfig, DensifySchedule, Group, LearningRates};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, Intrinsics};

const W: u32 = 48;
const H: u32 = 40;
const GAUSSIANS: usize = 32;
const FRAMES: usize = 12;
const KEYFRAMES: usize = 4;

/// The identity pose: at the origin, looking down +z.
fn camera() -> Camera {
    camera_of(W, H)
}

fn camera_of(w: u32, h: u32) -> Camera {
    let k = Intrinsics {
        fx: 0.9 * w as f32,
        fy: 0.9 * w as f32,
        cx: w as f32 / 2.0,
        cy: h as f32 / 2.0,
        width: w,
        height: h,
    };
    Camera::from_world_to_camera_matrix(k, Default::default()).unwrap()
}

struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (self.0 >> 40) as f32 / (1u64 << 24) as f32
    }
}

fn frame_time(f: usize) -> f64 {
    f as f64 / 10.0
}

fn keyframe_times() -> Vec<f64> {
    let end = frame_time(FRAMES - 1);
    (0..KEYFRAMES)
        .map(|k| end * k as f64 / (KEYFRAMES - 1) as f64)
        .collect()
}

/// Gaussian `i` is static for even `i`, else moves at a constant velocity (0.3 to 0.6 scene units
/// over the clip). `jitter` perturbs everything but the motion, alike at every keyframe.
fn scene(jitter: f32) -> FittedScene {
    let mut base = Rng(7);
    let mut noise = Rng(11);
    let mut gaussians = Vec::new();
    for i in 0..GAUSSIANS {
        let p = [
            base.unit() - 0.5,
            0.8 * (base.unit() - 0.5),
            1.0 + 0.2 * base.unit(),
        ];
        let v = if i % 2 == 0 {
            [0.0; 3]
        } else {
            [0.5 * (base.unit() - 0.5), 0.5 * (base.unit() - 0.5), 0.0]
        };
        let s = 0.04 + 0.04 * base.unit();
        let c = [base.unit(), base.unit(), base.unit()];
        let mut j = || (noise.unit() - 0.5) * jitter;
        let dp = [0.1 * j(), 0.1 * j(), 0.0];
        let ds = [1.0 + j(), 1.0 + j(), 1.0];
        let dc = [j(), j(), j()];
        gaussians.push((p, v, s, c, dp, ds, dc));
    }
    let keyframes = keyframe_times()
        .into_iter()
        .map(|t| {
            let mut cols = (vec![], vec![], vec![], vec![], vec![]);
            for (p, v, s, c, dp, ds, dc) in &gaussians {
                cols.0
                    .push(std::array::from_fn(|a| p[a] + v[a] * t as f32 + dp[a]));
                cols.1.push(ds.map(|d| s * d));
                cols.2.push([1.0, 0.0, 0.0, 0.0]);
                cols.3.push(0.8);
                cols.4
                    .push(std::array::from_fn(|a| (c[a] + dc[a]).clamp(0.0, 1.0)));
            }
            let set = GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap();
            (t, set)
        })
        .collect();
    FittedScene::new(keyframes).unwrap()
}

/// The truth rendered at every frame time.
fn frames(truth: &FittedScene) -> Vec<Frame> {
    let raster = CpuRasterizer::new();
    (0..FRAMES)
        .map(|f| {
            let time = frame_time(f);
            let set = truth.at(time).unwrap();
            let rgb = raster
                .render(&set, &camera(), &RenderOptions::default())
                .unwrap()
                .rgb;
            Frame {
                time,
                rgb,
                camera: camera(),
            }
        })
        .collect()
}

fn options(steps: u64) -> FitOptions {
    let mut rates = LearningRates::gaussian_splatting(1.0, steps);
    rates.groups[Group::Position.index()] = LearningRate::constant(2e-3);
    rates.groups[Group::Color.index()] = LearningRate::constant(2e-2);
    rates.groups[Group::LogScale.index()] = LearningRate::constant(1e-2);
    FitOptions {
        steps,
        holdout_every: 4,
        rates,
        static_tolerance: 0.03,
        ..FitOptions::default()
    }
}

fn finite(scene: &FittedScene) -> bool {
    scene.sets.iter().all(|s| {
        (0..s.len()).all(|i| {
            s.positions()[i]
                .iter()
                .chain(&s.scales()[i])
                .chain(&s.rotations()[i])
                .chain(&s.colors()[i])
                .chain(std::iter::once(&s.opacities()[i]))
                .all(|v| v.is_finite())
        })
    })
}

#[test]
fn fitting_raises_the_psnr_of_frames_it_never_saw() {
    let truth = scene(0.0);
    let frames = frames(&truth);
    let (fitted, report) = fit(&scene(0.6), &frames, &options(120), |_| Control::Continue).unwrap();
    assert_eq!(report.holdout_frames, vec![3, 7, 11]);
    let (before, after) = (
        report.holdout_psnr_before.unwrap(),
        report.holdout_psnr_after.unwrap(),
    );
    eprintln!(
        "held-out PSNR {before:.2} -> {after:.2} dB, train {:.2} dB, {} steps in {:.2} s",
        report.train_psnr_after, report.steps, report.seconds
    );
    // Measured 21.0 -> 39.5 dB; 10 dB is a clear margin that tolerates a change of rates.
    assert!(after > before + 10.0, "{before} -> {after}");
    // One camera, Gaussians moving in front of it: some pixels change, not all.
    let share = report.still_share.unwrap();
    assert!(share > 0.0 && share < 1.0, "{share}");
    assert_eq!((report.steps, fitted.len()), (120, GAUSSIANS));
}

#[test]
fn zero_steps_serve_exactly_the_initial_keyframe_sets() {
    let start = scene(0.6);
    let (fitted, report) = fit(&start, &frames(&scene(0.0)), &options(0), |_| {
        Control::Continue
    })
    .unwrap();
    assert_eq!((&fitted.times, &fitted.sets), (&start.times, &start.sets));
    assert_eq!(report.steps, 0);
    assert_eq!(report.holdout_psnr_after, report.holdout_psnr_before);
    // Only the Gaussians the start already holds still are static.
    assert_eq!(report.static_count, GAUSSIANS / 2);
}

/// A one-frame clip has no held-out frame (frame 0 is never the n-th), so the report has no
/// held-out PSNR; its one keyframe makes every Gaussian static.
#[test]
fn a_one_frame_clip_fits_with_no_holdout() {
    let truth = scene(0.0);
    let frame = frames(&truth).swap_remove(0);
    let one = |s: &FittedScene| FittedScene::new(vec![(0.0, s.sets[0].clone())]).unwrap();
    let (fitted, report) = fit(&one(&scene(0.6)), &[frame], &options(20), |_| {
        Control::Continue
    })
    .unwrap();
    assert!(report.holdout_frames.is_empty());
    assert_eq!(
        (report.holdout_psnr_before, report.holdout_psnr_after),
        (None, None)
    );
    assert!(report.train_psnr_after.is_finite());
    assert_eq!(report.static_count, GAUSSIANS);
    assert_eq!(fitted.sets.len(), 1);
    // One frame says nothing about what stays still.
    assert_eq!(report.still_share, None);
}

#[test]
fn an_all_black_clip_ends_finite() {
    let black: Vec<Frame> = frames(&scene(0.0))
        .into_iter()
        .map(|f| Frame {
            rgb: vec![0.0; f.rgb.len()],
            ..f
        })
        .collect();
    let (fitted, report) = fit(&scene(0.6), &black, &options(30), |_| Control::Continue).unwrap();
    assert!(finite(&fitted));
    assert!(report.curve.iter().all(|p| p.loss.is_finite()));
    assert!(report.holdout_psnr_after.unwrap() > report.holdout_psnr_before.unwrap());
    // One camera, and nothing in its frames changes: every pixel is still.
    assert_eq!(report.still_share, Some(1.0));
}

#[test]
fn learning_rates_a_million_times_too_high_end_finite() {
    let mut o = options(30);
    for g in &mut o.rates.groups {
        *g = LearningRate::constant(g.at(0) * 1e6);
    }
    o.eval_every = 10;
    let (fitted, report) =
        fit(&scene(0.6), &frames(&scene(0.0)), &o, |_| Control::Continue).unwrap();
    assert!(finite(&fitted), "no NaN or infinity in any keyframe set");
    assert!(report.curve.iter().all(|p| p.loss.is_finite()));
    assert!(report.holdout_psnr_after.unwrap().is_finite());
}

/// Densification with a threshold every Gaussian passes wants to double the scene; the budget of
/// 40 holds at every step and at the end.
#[test]
fn the_gaussian_budget_is_never_exceeded() {
    let mut o = options(30);
    o.max_gaussians = 40;
    o.densify = Some(DensifySchedule {
        config: DensifyConfig {
            grad_threshold: 0.0,
            ..DensifyConfig::default()
        },
        from: 5,
        until: 30,
        every: 5,
    });
    let mut most = 0;
    let (fitted, report) = fit(&scene(0.6), &frames(&scene(0.0)), &o, |p| {
        most = most.max(p.gaussians);
        Control::Continue
    })
    .unwrap();
    assert!(most <= 40 && report.gaussians <= 40);
    assert!(most > GAUSSIANS, "densification ran and grew the scene");
    assert!(fitted.sets.iter().all(|s| s.len() == fitted.len()));
    assert!(finite(&fitted));
    o.max_gaussians = GAUSSIANS - 1;
    assert!(fit(&scene(0.6), &frames(&scene(0.0)), &o, |_| Control::Continue).is_err());
}

/// With densification on, so the seeded split children are part of what must repeat.
#[test]
fn the_same_seed_gives_the_same_bits() {
    let frames = frames(&scene(0.0));
    let mut o = options(15);
    o.densify = Some(DensifySchedule {
        config: DensifyConfig {
            grad_threshold: 0.0,
            ..DensifyConfig::default()
        },
        from: 5,
        until: 15,
        every: 5,
    });
    o.max_gaussians = 48;
    let run = |o: &FitOptions| fit(&scene(0.6), &frames, o, |_| Control::Continue).unwrap();
    let ((a, ra), (b, rb)) = (run(&o), run(&o));
    assert!(a.len() > GAUSSIANS, "densification (seeded splits) ran");
    assert_eq!(a, b);
    assert_eq!(ra.curve, rb.curve);
    o.seed = 1;
    assert_ne!(run(&o).0, a, "another seed, another frame order");
}

/// Static Gaussians of the scene end static and share one value; every moving one does not. The
/// start holds the static ones still, so they are tied before the first step; the slowest moving
/// one travels 0.054 over the clip, wider than the tolerance (0.03 scene units, about 1.2 pixels
/// at the scene's depth).
#[test]
fn static_gaussians_end_static_and_moving_ones_do_not() {
    let truth = scene(0.0);
    let (fitted, _) = fit(&scene(0.6), &frames(&truth), &options(60), |_| {
        Control::Continue
    })
    .unwrap();
    for (i, &s) in fitted.static_mask.iter().enumerate() {
        let moving = truth.sets[0].positions()[i] != truth.sets[KEYFRAMES - 1].positions()[i];
        if moving {
            assert!(!s, "Gaussian {i} moves in the scene");
        } else {
            assert!(s, "Gaussian {i} is static in the scene");
            assert!(
                fitted
                    .sets
                    .iter()
                    .all(|set| set.positions()[i] == fitted.sets[0].positions()[i])
            );
        }
    }
}

#[test]
fn the_progress_callback_can_stop_the_fit() {
    let (_, report) = fit(&scene(0.6), &frames(&scene(0.0)), &options(50), |p| {
        if p.step >= 3 {
            Control::Stop
        } else {
            Control::Continue
        }
    })
    .unwrap();
    assert!(report.stopped);
    assert_eq!(report.steps, 3);
}

/// SSIM's window is 11×11: an 8×6 frame is scored by L1 alone and still fits.
#[test]
fn frames_smaller_than_the_ssim_window_fit_by_l1() {
    let truth = scene(0.0);
    let tiny = camera_of(8, 6);
    let rgb = CpuRasterizer::new()
        .render(&truth.sets[0], &tiny, &RenderOptions::default())
        .unwrap()
        .rgb;
    let frame = Frame {
        time: 0.0,
        rgb,
        camera: tiny,
    };
    let start = FittedScene::new(vec![(0.0, scene(0.6).sets[0].clone())]).unwrap();
    let (fitted, report) = fit(&start, &[frame], &options(10), |_| Control::Continue).unwrap();
    assert_eq!(report.steps, 10);
    assert!(finite(&fitted) && report.train_psnr_after.is_finite());
}

#[test]
fn inputs_that_describe_no_fit_are_refused() {
    let (start, frames) = (scene(0.6), frames(&scene(0.0)));
    let run = |frames: &[Frame], o: &FitOptions| fit(&start, frames, o, |_| Control::Continue);
    let mut all_held_out = options(5);
    all_held_out.holdout_every = 1;
    assert!(
        run(&frames, &all_held_out).is_err(),
        "nothing left to train on"
    );
    assert!(run(&[], &options(5)).is_err(), "no frames");
    let mut late = frames[0].clone();
    late.time = 5.0;
    assert!(
        run(&[late], &options(5)).is_err(),
        "outside the keyframes' span"
    );
    let mut short = frames[0].clone();
    short.rgb.pop();
    assert!(run(&[short], &options(5)).is_err(), "not the camera's size");
}

/// A still scene (every Gaussian static) seen from a still camera, started from keyframe sets
/// that wobble by a fraction of a pixel from keyframe to keyframe (as a feed-forward answer does):
/// the Gaussians are tied static before the first step and the fit ends with most of them
/// static, each sharing one value across the keyframes.
#[test]
fn a_still_scene_ends_mostly_static() {
    let still = |s: &FittedScene| {
        let first = s.sets[0].clone();
        FittedScene::new(s.times.iter().map(|&t| (t, first.clone())).collect()).unwrap()
    };
    let truth = still(&scene(0.0));
    let mut wobble = Rng(3);
    let mut start = still(&scene(0.6));
    for set in &mut start.sets {
        let moved: Vec<[f32; 3]> = set
            .positions()
            .iter()
            .map(|p| {
                let mut d = || 0.006 * (wobble.unit() - 0.5);
                [p[0] + d(), p[1] + d(), p[2]]
            })
            .collect();
        *set = GaussianSet::new(
            moved,
            set.scales().to_vec(),
            set.rotations().to_vec(),
            set.opacities().to_vec(),
            set.colors().to_vec(),
        )
        .unwrap();
    }
    let mut o = options(120);
    o.static_tolerance = 0.0;
    let (fitted, report) = fit(&start, &frames(&truth), &o, |_| Control::Continue).unwrap();
    eprintln!("{} of {GAUSSIANS} static", report.static_count);
    assert!(
        report.static_count * 4 >= GAUSSIANS * 3,
        "{}",
        report.static_count
    );
    for (i, _) in fitted.static_mask.iter().enumerate().filter(|(_, s)| **s) {
        assert!(
            fitted
                .sets
                .iter()
                .all(|s| s.positions()[i] == fitted.sets[0].positions()[i])
        );
    }
    assert!(report.holdout_psnr_after > report.holdout_psnr_before);
}

/// A start that holds the moving Gaussians still (each at its mean position at every keyframe)
/// ties them before the first step; the frames pull their keyframes apart consistently, so they
/// are untied and end moving, while the static ones stay static.
#[test]
fn a_moving_gaussian_tied_on_its_starts_say_is_untied() {
    let truth = scene(0.0);
    let mut start = scene(0.6);
    let k = start.sets.len();
    let mut positions: Vec<Vec<[f32; 3]>> =
        start.sets.iter().map(|s| s.positions().to_vec()).collect();
    for i in (1..GAUSSIANS).step_by(2) {
        let mean: [f32; 3] =
            std::array::from_fn(|a| positions.iter().map(|p| p[i][a]).sum::<f32>() / k as f32);
        for p in &mut positions {
            p[i] = mean;
        }
    }
    for (set, p) in start.sets.iter_mut().zip(positions) {
        *set = GaussianSet::new(
            p,
            set.scales().to_vec(),
            set.rotations().to_vec(),
            set.opacities().to_vec(),
            set.colors().to_vec(),
        )
        .unwrap();
    }
    let (fitted, report) = fit(&start, &frames(&truth), &options(240), |_| {
        Control::Continue
    })
    .unwrap();
    let moving_static = (1..GAUSSIANS)
        .step_by(2)
        .filter(|&i| fitted.static_mask[i])
        .count();
    let still_static = (0..GAUSSIANS)
        .step_by(2)
        .filter(|&i| fitted.static_mask[i])
        .count();
    eprintln!(
        "moving ones static: {moving_static}; still ones static: {still_static}; {} dB",
        report.holdout_psnr_after.unwrap()
    );
    // Measured: 4 of the 16 moving ones end static (tied while their neighbours' errors pulled
    // them as much as their own motion), 12 of the 16 still ones do.
    assert!(moving_static * 3 <= GAUSSIANS / 2, "{moving_static}");
    assert!(still_static * 3 >= GAUSSIANS, "{still_static}");
}

/// The angle (radians) and the distance between two cameras' poses.
fn pose_error(a: &Camera, b: &Camera) -> (f32, f32) {
    let (ra, ta) = (a.world_to_camera(), b.world_to_camera());
    let relative = ra.matrix3 * ta.matrix3.transpose();
    let trace = relative.x_axis.x + relative.y_axis.y + relative.z_axis.z;
    let angle = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos();
    (angle, (ra.translation - ta.translation).length())
}

/// The given camera of training frame 0 is off the one that took it (rotated 0.03 rad, about
/// 1.3 px, and shifted 0.02); refining the cameras moves it back toward the truth, while the
/// held-out frames keep their given cameras and a fit without refinement keeps every camera.
#[test]
fn a_perturbed_camera_moves_back_toward_the_truth() {
    let truth = scene(0.0);
    let mut frames = frames(&truth);
    let off = glam::Affine3A::from_rotation_translation(
        glam::Quat::from_rotation_y(0.03),
        glam::Vec3::new(0.02, 0.0, 0.0),
    );
    frames[0].camera = Camera::new(
        *frames[0].camera.intrinsics(),
        off * frames[0].camera.world_to_camera(),
    )
    .unwrap();
    let mut o = options(120);
    o.refine_cameras = true;
    o.camera_rates = [2e-3, 2e-3, 0.0];
    o.camera_prior = 1e-3;
    let (_, report) = fit(&truth, &frames, &o, |_| Control::Continue).unwrap();
    let before = pose_error(&frames[0].camera, &camera());
    let after = pose_error(&report.cameras[0], &camera());
    eprintln!(
        "rotation {} -> {} rad, translation {} -> {}",
        before.0, after.0, before.1, after.1
    );
    assert!(after.0 < 0.5 * before.0, "{before:?} -> {after:?}");
    assert!(after.1 < before.1, "{before:?} -> {after:?}");
    assert_eq!(
        report.cameras[3], frames[3].camera,
        "held out: the given camera"
    );
    o.refine_cameras = false;
    let (_, kept) = fit(&truth, &frames, &o, |_| Control::Continue).unwrap();
    assert!(
        kept.cameras
            .iter()
            .zip(&frames)
            .all(|(c, f)| *c == f.camera)
    );
}
