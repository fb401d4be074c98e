//! Fits keyframe sets to a folder of frames (PNG or JPEG, sorted by name) seen by one static
//! camera, from a grid start, and prints the held-out PSNR against time as CSV: what the fit buys
//! on frames it never trained on.
//!
//!     cargo run --release -p c4g-fit --example fit_frames -- \
//!         [--frames DIR (../shared/data/bedroom/frames)] [--count 24] [--stride 2] [--fps 30] \
//!         [--width 64] [--keyframes 4] [--grid 16] [--steps 300] [--every 25] \
//!         [--holdout 8] [--budget N (densify under it; none by default)] [--seed 0]
//!
//! The start is a stand-in for a feed-forward answer: a `grid`×`grid·H/W` grid of Gaussians at
//! depth 1 filling the view, each coloured by the first frame's pixel under it, the same set at
//! every keyframe (so the fit has to discover the motion). The camera is the identity with
//! `fx = fy = width`. A real clip's camera moves; a static camera is this example's assumption.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::path::PathBuf;

use c4g_fit::{Control, FitOptions, FittedScene, Frame, fit};
use c4g_optim::schedule::LearningRate;
use c4g_optim::{DensifyConfig, DensifySchedule, Group, LearningRates};
use c4g_scene::{Camera, GaussianSet, Intrinsics};

struct Args {
    frames: PathBuf,
    count: usize,
    stride: usize,
    fps: f64,
    width: u32,
    keyframes: usize,
    grid: usize,
    steps: u64,
    every: u64,
    holdout: usize,
    budget: Option<usize>,
    seed: u64,
}

fn args() -> Args {
    let mut a = Args {
        frames: PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/data/bedroom/frames"),
        count: 24,
        stride: 2,
        fps: 30.0,
        width: 64,
        keyframes: 4,
        grid: 16,
        steps: 300,
        every: 25,
        holdout: 8,
        budget: None,
        seed: 0,
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    for pair in argv.chunks(2) {
        let v = pair.get(1).cloned().unwrap_or_default();
        match pair[0].as_str() {
            "--frames" => a.frames = v.into(),
            "--count" => a.count = v.parse().expect("--count"),
            "--stride" => a.stride = v.parse().expect("--stride"),
            "--fps" => a.fps = v.parse().expect("--fps"),
            "--width" => a.width = v.parse().expect("--width"),
            "--keyframes" => a.keyframes = v.parse().expect("--keyframes"),
            "--grid" => a.grid = v.parse().expect("--grid"),
            "--steps" => a.steps = v.parse().expect("--steps"),
            "--every" => a.every = v.parse().expect("--every"),
            "--holdout" => a.holdout = v.parse().expect("--holdout"),
            "--budget" => a.budget = Some(v.parse().expect("--budget")),
            "--seed" => a.seed = v.parse().expect("--seed"),
            other => panic!("unknown argument {other}"),
        }
    }
    a
}

/// The frames, resized to `width` (keeping the aspect), with their times.
fn load(a: &Args) -> (Vec<(f64, Vec<f32>)>, u32, u32) {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(&a.frames)
        .expect("the frames folder")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("");
            ["png", "jpg", "jpeg"].contains(&ext.to_ascii_lowercase().as_str())
        })
        .collect();
    paths.sort();
    let mut size = (0, 0);
    let frames = paths
        .iter()
        .step_by(a.stride.max(1))
        .take(a.count)
        .enumerate()
        .map(|(i, p)| {
            let img = image::open(p).expect("a frame").to_rgb8();
            let h = (f64::from(a.width) * f64::from(img.height()) / f64::from(img.width())).round();
            size = (a.width, (h as u32).max(11));
            let small = image::imageops::resize(
                &img,
                size.0,
                size.1,
                image::imageops::FilterType::Triangle,
            );
            let rgb = small
                .as_raw()
                .iter()
                .map(|&v| f32::from(v) / 255.0)
                .collect();
            (i as f64 * a.stride as f64 / a.fps, rgb)
        })
        .collect();
    (frames, size.0, size.1)
}

fn grid_start(first: &[f32], w: u32, h: u32, grid: usize) -> GaussianSet {
    let (gw, gh) = (
        grid,
        (grid as f64 * f64::from(h) / f64::from(w)).round().max(1.0) as usize,
    );
    let spacing = 1.0 / gw as f32;
    let mut cols = (vec![], vec![], vec![], vec![], vec![]);
    for y in 0..gh {
        for x in 0..gw {
            let (u, v) = ((x as f32 + 0.5) / gw as f32, (y as f32 + 0.5) / gh as f32);
            let (px, py) = ((u * w as f32) as usize, (v * h as f32) as usize);
            let at = 3 * (py * w as usize + px);
            // fx = width at depth 1: the view is 1 wide and h/w high.
            cols.0.push([u - 0.5, (v - 0.5) * h as f32 / w as f32, 1.0]);
            cols.1.push([0.6 * spacing, 0.6 * spacing, 0.1 * spacing]);
            cols.2.push([1.0, 0.0, 0.0, 0.0]);
            cols.3.push(0.7);
            cols.4.push([first[at], first[at + 1], first[at + 2]]);
        }
    }
    GaussianSet::new(cols.0, cols.1, cols.2, cols.3, cols.4).unwrap()
}

fn main() {
    let a = args();
    let (frames, w, h) = load(&a);
    assert!(!frames.is_empty(), "no frames in {}", a.frames.display());
    let camera = Camera::from_world_to_camera_matrix(
        Intrinsics {
            fx: w as f32,
            fy: w as f32,
            cx: w as f32 / 2.0,
            cy: h as f32 / 2.0,
            width: w,
            height: h,
        },
        Default::default(),
    )
    .unwrap();
    let end = frames.last().map_or(0.0, |f| f.0);
    let k = a.keyframes.max(1).min(frames.len());
    let set = grid_start(&frames[0].1, w, h, a.grid);
    let keyframes = (0..k)
        .map(|i| {
            let t = if k == 1 {
                0.0
            } else {
                end * i as f64 / (k - 1) as f64
            };
            (t, set.clone())
        })
        .collect();
    let start = FittedScene::new(keyframes).unwrap();
    let frames: Vec<Frame> = frames
        .into_iter()
        .map(|(time, rgb)| Frame { time, rgb, camera })
        .collect();
    let mut rates = LearningRates::gaussian_splatting(1.0, a.steps);
    rates.groups[Group::Position.index()] = LearningRate::constant(1e-3);
    rates.groups[Group::Color.index()] = LearningRate::constant(1e-2);
    let options = FitOptions {
        steps: a.steps,
        holdout_every: a.holdout,
        seed: a.seed,
        rates,
        eval_every: a.every,
        max_gaussians: a.budget.unwrap_or(usize::MAX),
        densify: a.budget.map(|_| DensifySchedule {
            config: DensifyConfig::default(),
            from: 50,
            until: a.steps,
            every: 50,
        }),
        ..FitOptions::default()
    };
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "# {} frames {w}x{h}, {k} keyframes, {} Gaussians, {cores} cores",
        frames.len(),
        set.len()
    );
    println!("step,seconds,loss,gaussians,holdout_psnr");
    let (_, report) = fit(&start, &frames, &options, |p| {
        if let Some(psnr) = p.holdout_psnr {
            println!(
                "{},{:.2},{:.5},{},{psnr:.3}",
                p.step, p.seconds, p.loss, p.gaussians
            );
        }
        Control::Continue
    })
    .unwrap();
    println!(
        "# held out {:?}: {:.2} -> {:.2} dB; train {:.2} dB; {} steps in {:.1} s; {} static",
        report.holdout_frames,
        report.holdout_psnr_before.unwrap_or(f64::NAN),
        report.holdout_psnr_after.unwrap_or(f64::NAN),
        report.train_psnr_after,
        report.steps,
        report.seconds,
        report.static_count
    );
}
