//! The single-image fit learns: a few steps on a small image lower the loss, with and without
//! densification. The target is a render of a known scene (so the fit can reach it); the start
//! is that scene displaced, rescaled and recoloured.
#![allow(clippy::unwrap_used, clippy::expect_used)]

use c4g_optim::schedule::LearningRate;
use c4g_optim::{DensifyConfig, DensifySchedule, FitConfig, Group, ImageFit, LearningRates};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, Intrinsics};
/// A camera at the origin looking down +z (the identity pose).
fn camera(w: u32, h: u32) -> Camera {
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

fn scene(n: usize, seed: u64, jitter: f32) -> GaussianSet {
    let mut rng = Rng(seed);
    let mut base = Rng(99);
    let mut cols = (vec![], vec![], vec![], vec![], vec![]);
    for _ in 0..n {
        let p = [
            base.unit() - 0.5,
            base.unit() - 0.5,
            1.0 + 0.2 * base.unit(),
        ];
        let s = 0.03 + 0.05 * base.unit();
        let c = [base.unit(), base.unit(), base.unit()];
        let mut j = || (rng.unit() - 0.5) * jitter;
        cols.0.push([p[0] + 0.1 * j(), p[1] + 0.1 * j(), p[2]]);
        cols.1.push([s * (1.0 + j()), s * (1.0 + j()), s]);
        cols.2.push([1.0, 0.0, 0.0, 0.0]);
        cols.3.push(0.7);
        cols.4.push(c.map(|v| (v + j()).clamp(0.0, 1.0)));
    }
    GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap()
}

fn config(densify: Option<DensifySchedule>) -> FitConfig {
    let mut rates = LearningRates::gaussian_splatting(1.0, 100);
    rates.groups[Group::Position.index()] = LearningRate::constant(2e-3);
    rates.groups[Group::Color.index()] = LearningRate::constant(2e-2);
    rates.groups[Group::LogScale.index()] = LearningRate::constant(1e-2);
    FitConfig {
        lambda_dssim: 0.2,
        rates,
        adam: Default::default(),
        clip_norm: None,
        densify,
        extent: 1.0,
        render: RenderOptions {
            features: false,
            ..RenderOptions::default()
        },
    }
}

#[test]
fn a_few_steps_lower_the_loss() {
    let camera = camera(48, 40);
    let target = CpuRasterizer::new()
        .render(&scene(30, 1, 0.0), &camera, &RenderOptions::default())
        .unwrap()
        .rgb;
    let mut fit = ImageFit::new(&scene(30, 2, 0.6), camera, target, config(None)).unwrap();
    let first = fit.step().unwrap();
    let mut last = first;
    for _ in 0..40 {
        last = fit.step().unwrap();
    }
    assert!(
        last.loss < 0.7 * first.loss,
        "loss {} → {}",
        first.loss,
        last.loss
    );
    assert!(
        last.psnr > first.psnr + 2.0,
        "PSNR {} → {}",
        first.psnr,
        last.psnr
    );
}

#[test]
fn densification_adds_gaussians_within_the_budget_and_the_loss_still_falls() {
    let camera = camera(48, 40);
    let target = CpuRasterizer::new()
        .render(&scene(60, 1, 0.0), &camera, &RenderOptions::default())
        .unwrap()
        .rgb;
    let schedule = DensifySchedule {
        config: DensifyConfig {
            grad_threshold: 1e-5,
            budget: 45,
            ..DensifyConfig::default()
        },
        from: 10,
        until: 30,
        every: 10,
    };
    let start = scene(60, 3, 0.6).select(&[true, false].repeat(30)).unwrap();
    let mut fit = ImageFit::new(&start, camera, target, config(Some(schedule))).unwrap();
    let first = fit.step().unwrap();
    let mut last = first;
    let mut grew = false;
    for _ in 0..40 {
        last = fit.step().unwrap();
        grew |= last.densified.is_some_and(|r| r.cloned + r.split > 0);
        assert!(last.gaussians <= 45);
    }
    assert!(grew, "densification ran and added Gaussians");
    assert!(fit.set().len() > 30);
    assert!(
        last.loss < 0.8 * first.loss,
        "loss {} → {}",
        first.loss,
        last.loss
    );
}
