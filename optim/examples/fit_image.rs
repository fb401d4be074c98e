//! Fits Gaussians to one image, a 256² crop of a frame of a shared real clip, for a time budget,
//! and prints the curve (PSNR against time) as CSV rows: what the CPU gradients buy.
//!
//!     cargo run --release -p c4g-optim --example fit_image -- \
//!         [--frame ../shared/data/bedroom/frames/00000.jpg] [--size 256] [--seconds 120] \
//!         [--init random|grid] [--gaussians 4000] [--budget 30000] [--lambda 0.2] [--every 2] \
//!         [--save final.png] [--target frame.png]
//!
//! Starts: `random` (positions uniform over the view at depth 1 ± 5 %, random colours, opacity
//! 0.5, σ about the mean spacing), `grid` (a regular grid with each Gaussian coloured by the
//! target pixel under it: a cheap stand-in for a feed-forward start) or `decoded:PATH` (a set the
//! model decoded, packed canonical f32; with `--target PNG`, the frame as the model saw it, at
//! `--size`², since the set is in that view: the centre square of the frame, resized). Densification (3DGS's clone, split and prune, threshold 2e-4 NDC) runs every 100
//! steps under the `--budget`. The camera is the identity with C4G's default intrinsics.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::PathBuf;
use std::time::Instant;

use c4g_optim::schedule::{LearningRate, Schedule};
use c4g_optim::{DensifyConfig, DensifySchedule, FitConfig, Group, ImageFit, LearningRates};
use c4g_renderer::RenderOptions;
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};

struct Args {
    frame: PathBuf,
    size: u32,
    seconds: f64,
    init: String,
    gaussians: usize,
    budget: usize,
    lambda: f64,
    every: u64,
    save: Option<PathBuf>,
    target: Option<PathBuf>,
}

fn args() -> Args {
    let mut a = Args {
        frame: PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/data/bedroom/frames/00000.jpg"),
        size: 256,
        seconds: 120.0,
        init: "random".into(),
        gaussians: 4000,
        budget: 30_000,
        lambda: 0.2,
        every: 2,
        save: None,
        target: None,
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    for pair in argv.chunks(2) {
        let value = pair.get(1).cloned().unwrap_or_default();
        match pair[0].as_str() {
            "--frame" => a.frame = value.into(),
            "--size" => a.size = value.parse().expect("--size"),
            "--seconds" => a.seconds = value.parse().expect("--seconds"),
            "--init" => a.init = value,
            "--gaussians" => a.gaussians = value.parse().expect("--gaussians"),
            "--budget" => a.budget = value.parse().expect("--budget"),
            "--lambda" => a.lambda = value.parse().expect("--lambda"),
            "--every" => a.every = value.parse().expect("--every"),
            "--save" => a.save = Some(value.into()),
            "--target" => a.target = Some(value.into()),
            other => panic!("unknown argument {other}"),
        }
    }
    a
}

/// The centre `size`² crop of the frame, RGB in 0..1 (a `size`² image is taken whole).
fn target(path: &PathBuf, size: u32) -> Vec<f32> {
    let image = image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8();
    let (w, h) = image.dimensions();
    assert!(
        w >= size && h >= size,
        "{}: smaller than {size}²",
        path.display()
    );
    let crop =
        image::imageops::crop_imm(&image, (w - size) / 2, (h - size) / 2, size, size).to_image();
    crop.pixels()
        .flat_map(|p| p.0.map(|v| f32::from(v) / 255.0))
        .collect()
}

struct Rng(u64);

impl Rng {
    fn unit(&mut self) -> f32 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
    }
}

/// `n` Gaussians at depth about 1 covering the view; colours random or from `target`.
fn start(camera: &Camera, n: usize, target: Option<&[f32]>) -> GaussianSet {
    let k = camera.intrinsics();
    let (w, h) = (k.width, k.height);
    let mut rng = Rng(1);
    let spacing = (f64::from(w * h) / n as f64).sqrt() as f32;
    let side = (n as f64).sqrt().ceil() as usize;
    let mut cols = (vec![], vec![], vec![], vec![], vec![]);
    for i in 0..n {
        let (u, v, z) = match target {
            // A regular grid, nominal depth 1.
            Some(_) => (
                ((i % side) as f32 + 0.5) * w as f32 / side as f32,
                ((i / side) as f32 + 0.5) * h as f32 / side as f32,
                1.0,
            ),
            None => (
                rng.unit() * w as f32,
                rng.unit() * h as f32,
                0.95 + 0.1 * rng.unit(),
            ),
        };
        cols.0
            .push([(u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z]);
        let sigma = 0.5 * spacing * z / k.fx;
        cols.1.push([sigma; 3]);
        let q = [0; 4].map(|_| rng.unit() - 0.5);
        cols.2.push(q);
        cols.3.push(0.5);
        cols.4.push(match target {
            Some(t) => {
                let p = (v as usize).min(h as usize - 1) * w as usize
                    + (u as usize).min(w as usize - 1);
                [t[3 * p], t[3 * p + 1], t[3 * p + 2]]
            }
            None => [rng.unit(), rng.unit(), rng.unit()],
        });
    }
    GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap()
}

/// A set decoded by the model: packed canonical Gaussians (14 little-endian f32 each).
fn decoded(path: &str) -> GaussianSet {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{path}: {e}"));
    let floats: Vec<f32> = bytes
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    GaussianSet::from_canonical(&floats).unwrap()
}

fn main() {
    let a = args();
    let target = target(a.target.as_ref().unwrap_or(&a.frame), a.size);
    // The identity pose (a 4×4 matrix's default).
    let camera = Camera::from_world_to_camera_matrix(
        NormalizedIntrinsics::C4G_DEFAULT.to_pixels(a.size, a.size),
        Default::default(),
    )
    .unwrap();
    let init = match a.init.as_str() {
        "random" => start(&camera, a.gaussians, None),
        "grid" => start(&camera, a.gaussians, Some(&target)),
        other => match other.strip_prefix("decoded:") {
            Some(path) => decoded(path),
            None => panic!("--init {other}: random, grid or decoded:PATH"),
        },
    };
    // Rates for a plane of Gaussians a unit away (a pixel is 1/fx ≈ 0.0045 units): positions
    // from about half a pixel a step down to a fiftieth, the rest 3DGS's scaled for a short run.
    let steps_guess = 3000;
    let mut rates = LearningRates::gaussian_splatting(1.0, steps_guess);
    rates.groups[Group::Position.index()] = LearningRate {
        schedule: Schedule::Exponential {
            start: 2e-3,
            end: 1e-4,
            steps: steps_guess,
        },
        warmup: None,
    };
    rates.groups[Group::LogScale.index()] = LearningRate::constant(1e-2);
    rates.groups[Group::Rotation.index()] = LearningRate::constant(5e-3);
    rates.groups[Group::Color.index()] = LearningRate::constant(1e-2);
    let config = FitConfig {
        lambda_dssim: a.lambda,
        rates,
        adam: Default::default(),
        clip_norm: None,
        densify: Some(DensifySchedule {
            config: DensifyConfig {
                budget: a.budget,
                ..DensifyConfig::default()
            },
            from: 100,
            until: u64::MAX,
            every: 100,
        }),
        extent: 1.0,
        render: RenderOptions {
            features: false,
            background: [0.0; 3],
            ..RenderOptions::default()
        },
    };
    let render = config.render.clone();
    let mut fit = ImageFit::new(&init, camera, target, config).unwrap();
    println!("seconds,step,psnr_db,loss,gaussians");
    let clock = Instant::now();
    let mut best = f64::MIN;
    loop {
        let r = fit.step().unwrap();
        let t = clock.elapsed().as_secs_f64();
        best = best.max(r.psnr);
        if r.step.is_multiple_of(a.every) {
            println!(
                "{t:.2},{},{:.3},{:.5},{}",
                r.step, r.psnr, r.loss, r.gaussians
            );
        }
        if t >= a.seconds {
            eprintln!(
                "{} init, {} steps in {t:.1} s ({:.1} steps/s), last PSNR {:.2} dB, best {best:.2} dB, {} Gaussians",
                a.init,
                r.step + 1,
                (r.step + 1) as f64 / t,
                r.psnr,
                r.gaussians
            );
            break;
        }
    }
    if let Some(path) = &a.save {
        use c4g_renderer::{CpuRasterizer, Rasterizer};
        let image = CpuRasterizer::new()
            .render(&fit.set(), &camera, &render)
            .unwrap();
        let bytes: Vec<u8> = image
            .rgb
            .iter()
            .map(|v| (v.clamp(0.0, 1.0) * 255.0).round() as u8)
            .collect();
        image::RgbImage::from_raw(a.size, a.size, bytes)
            .unwrap()
            .save(path)
            .unwrap();
    }
}
