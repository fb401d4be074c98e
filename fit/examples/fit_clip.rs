//! Measures the fit on a real clip as the service would run it (issue 38's acceptance; the numbers
//! of docs/tradeoffs.md, "Fitting a clip"): the feed-forward answer of the default model, then
//! fits at the presets and one from a random start with the same steps, each scored on the
//! held-out frames.
//!
//!     source scripts/env.sh   # ORT_DYLIB_PATH, as the service finds ONNX Runtime
//!     cargo run --release -p c4g-fit --example fit_clip -- \
//!         [--frames DIR (../shared/data/bedroom/frames)] [--fps 30] [--name bedroom] \
//!         [--model models/c4g-tiny] [--presets fast,default] [--random fast] \
//!         [--steps N (overrides the presets' steps)] [--budget S (their time budget)]
//!         [--static-pixels P (the static tolerance in pixels)] [--still-threshold T (0: off)] [--smoothness W] [--resolution PX]
//!         [--keyframe-every N] [--refine-cameras true] [--csv FILE]
//!
//! A video is decoded to a folder of frames beforehand (`ffmpeg -i clip.mp4 DIR/%05d.png`).
//!
//! What it does, in the service's terms: four context frames spread over the clip (first and
//! last included, as intake samples them) go through the package's preprocessing (centre square
//! crop, resize) and the encoder; the feed-forward sets are decoded at [`keyframe_times`]; the
//! start is [`FittedScene::new`] through them, then [`cover_frame`] for the frame outside the
//! crop. Every frame is seen by the clip's static camera: the identity pose with the model's
//! intrinsics mapped from the crop (the centred square of side `min(W, H)`) to the whole frame.
//!
//! Scores, on the held-out frames (every `holdout_every`-th of the frames used, never trained on),
//! rendered at 256 px on the long side: PSNR and SSIM on the square centre crop (what the model
//! sees, where the feed-forward answer has Gaussians) and on the full frame. "feed-forward" is the
//! model's own decode at each held-out time (what is served without a fit); "start" is the fit's
//! start (keyframes interpolated, plus the cover) before any step.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;

use c4g_engine::{ContextFrame, Engine, EngineOptions};
use c4g_fit::{
    Control, FitSettings, FittedScene, Frame, Preset, cover_frame, fit, holdout_frames,
    keyframe_times,
};
use c4g_renderer::fidelity::{psnr, ssim};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, Intrinsics, NormalizedIntrinsics};
use image::RgbImage;

/// Long side of the scoring renders, px.
const SCORE_SIDE: u32 = 256;
const CONTEXT_FRAMES: usize = 4;

struct Args {
    frames: PathBuf,
    fps: f64,
    name: String,
    model: PathBuf,
    presets: Vec<Preset>,
    random: Vec<Preset>,
    steps: Option<u64>,
    budget: Option<f64>,
    static_pixels: Option<f64>,
    still_threshold: Option<f64>,
    smoothness: Option<f64>,
    refine_cameras: bool,
    resolution: Option<u32>,
    keyframe_every: Option<usize>,
    csv: Option<PathBuf>,
}

fn presets(v: &str) -> Vec<Preset> {
    v.split(',')
        .filter(|s| !s.is_empty())
        .map(|s| Preset::parse(s).unwrap_or_else(|| panic!("unknown preset {s}")))
        .collect()
}

fn args() -> Args {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let mut a = Args {
        frames: root.join("../shared/data/bedroom/frames"),
        fps: 30.0,
        name: "clip".into(),
        model: root.join("models/c4g-tiny"),
        presets: vec![Preset::Fast, Preset::Default],
        random: vec![Preset::Fast],
        steps: None,
        budget: None,
        static_pixels: None,
        still_threshold: None,
        smoothness: None,
        refine_cameras: false,
        resolution: None,
        keyframe_every: None,
        csv: None,
    };
    let argv: Vec<String> = std::env::args().skip(1).collect();
    for pair in argv.chunks(2) {
        let v = pair.get(1).cloned().unwrap_or_default();
        match pair[0].as_str() {
            "--frames" => a.frames = v.into(),
            "--fps" => a.fps = v.parse().expect("--fps"),
            "--name" => a.name = v,
            "--model" => a.model = v.into(),
            "--presets" => a.presets = presets(&v),
            "--random" => a.random = presets(&v),
            "--steps" => a.steps = Some(v.parse().expect("--steps")),
            "--budget" => a.budget = Some(v.parse().expect("--budget")),
            "--static-pixels" => a.static_pixels = Some(v.parse().expect("--static-pixels")),
            "--still-threshold" => a.still_threshold = Some(v.parse().expect("--still-threshold")),
            "--refine-cameras" => a.refine_cameras = v == "true",
            "--smoothness" => a.smoothness = Some(v.parse().expect("--smoothness")),
            "--resolution" => a.resolution = Some(v.parse().expect("--resolution")),
            "--keyframe-every" => a.keyframe_every = Some(v.parse().expect("--keyframe-every")),
            "--csv" => a.csv = Some(v.into()),
            other => panic!("unknown argument {other}"),
        }
    }
    a
}

/// The clip's frames, in name order.
fn frame_paths(dir: &Path) -> Vec<PathBuf> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .expect("the frames folder")
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let ext = p.extension().and_then(|e| e.to_str()).unwrap_or("");
            ["png", "jpg", "jpeg"].contains(&ext.to_ascii_lowercase().as_str())
        })
        .collect();
    paths.sort();
    paths
}

/// `k` of `0..n` spread evenly, first and last included (the service's intake sampling).
fn spread(n: usize, k: usize) -> Vec<usize> {
    if k <= 1 || n <= 1 {
        return (0..n.min(k.max(1))).collect();
    }
    let k = k.min(n);
    let mut picked: Vec<usize> = (0..k)
        .map(|i| (i * (n - 1) + (k - 1) / 2) / (k - 1))
        .collect();
    picked.dedup();
    picked
}

/// The static camera at `w` × `h`: identity pose, the model's intrinsics on the centre square.
fn camera(w: u32, h: u32) -> Camera {
    let k = NormalizedIntrinsics::C4G_DEFAULT;
    let side = w.min(h) as f32;
    let (ox, oy) = ((w as f32 - side) / 2.0, (h as f32 - side) / 2.0);
    let intrinsics = Intrinsics {
        fx: k.fx * side,
        fy: k.fy * side,
        cx: k.cx * side + ox,
        cy: k.cy * side + oy,
        width: w,
        height: h,
    };
    Camera::from_world_to_camera_matrix(intrinsics, Default::default()).unwrap()
}

/// `img` at `long` px on its long side, RGB in [0, 1].
fn working(img: &RgbImage, long: u32) -> (u32, u32, Vec<f32>) {
    let (w, h) = img.dimensions();
    let (sw, sh) = if w >= h {
        (
            long,
            ((long as f64 * h as f64 / w as f64).round() as u32).max(1),
        )
    } else {
        (
            ((long as f64 * w as f64 / h as f64).round() as u32).max(1),
            long,
        )
    };
    let small = image::imageops::resize(img, sw, sh, image::imageops::FilterType::Triangle);
    let rgb = small
        .as_raw()
        .iter()
        .map(|&v| f32::from(v) / 255.0)
        .collect();
    (sw, sh, rgb)
}

/// The centred square of an RGB image.
fn crop(rgb: &[f32], w: u32, h: u32) -> (Vec<f32>, u32) {
    let side = w.min(h);
    let (x0, y0) = ((w - side) / 2, (h - side) / 2);
    let mut out = Vec::with_capacity(3 * (side * side) as usize);
    for y in y0..y0 + side {
        let row = 3 * (y * w + x0) as usize;
        out.extend_from_slice(&rgb[row..row + 3 * side as usize]);
    }
    (out, side)
}

#[derive(Default, Clone, Copy)]
struct Score {
    crop_psnr: f64,
    crop_ssim: f64,
    full_psnr: f64,
    full_ssim: f64,
}

/// Mean scores of the sets (one per held-out frame) against the held-out frames at 256 px.
fn score(sets: &[GaussianSet], truths: &[(u32, u32, Vec<f32>)]) -> Score {
    let raster = CpuRasterizer::new();
    let options = RenderOptions {
        features: false,
        ..RenderOptions::default()
    };
    let mut s = Score::default();
    for (set, (w, h, truth)) in sets.iter().zip(truths) {
        let image = raster.render(set, &camera(*w, *h), &options).unwrap();
        let rgb: Vec<f32> = image.rgb.iter().map(|v| v.clamp(0.0, 1.0)).collect();
        let ((rc, side), (tc, _)) = (crop(&rgb, *w, *h), crop(truth, *w, *h));
        s.crop_psnr += psnr(&rc, &tc, side, side, None).unwrap();
        s.crop_ssim += ssim(&rc, &tc, side, side, None).unwrap();
        s.full_psnr += psnr(&rgb, truth, *w, *h, None).unwrap();
        s.full_ssim += ssim(&rgb, truth, *w, *h, None).unwrap();
    }
    let n = sets.len().max(1) as f64;
    Score {
        crop_psnr: s.crop_psnr / n,
        crop_ssim: s.crop_ssim / n,
        full_psnr: s.full_psnr / n,
        full_ssim: s.full_ssim / n,
    }
}

/// A start of `n` Gaussians with nothing of the model in it: uniform over the frame, depth
/// uniform within ±50 % of `depth`, random colours, the same at every keyframe.
fn random_start(times: &[f64], n: usize, depth: f32, cam: &Camera, seed: u64) -> FittedScene {
    let mut state = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
    let mut uniform = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f32 / (1u64 << 53) as f32
    };
    let k = cam.intrinsics();
    let spacing = (k.width as f32 * k.height as f32 / n.max(1) as f32).sqrt();
    let mut g = Vec::with_capacity(n);
    for _ in 0..n {
        let (u, v) = (uniform() * k.width as f32, uniform() * k.height as f32);
        let z = depth * (0.5 + uniform());
        g.push(c4g_scene::Gaussian {
            position: glam::Vec3::new((u - k.cx) / k.fx * z, (v - k.cy) / k.fy * z, z),
            scale: glam::Vec3::splat(0.7 * spacing * z / k.fx),
            rotation: glam::Quat::IDENTITY,
            opacity: 0.5,
            color: glam::Vec3::new(uniform(), uniform(), uniform()),
        });
    }
    let set = GaussianSet::from_gaussians(g);
    FittedScene::new(times.iter().map(|&t| (t, set.clone())).collect()).unwrap()
}

fn median_depth(set: &GaussianSet) -> f64 {
    let mut z: Vec<f32> = set
        .positions()
        .iter()
        .map(|p| p[2])
        .filter(|z| *z > 0.0)
        .collect();
    z.sort_by(f32::total_cmp);
    z.get(z.len() / 2).map_or(1.0, |&z| f64::from(z))
}

struct Clip {
    images: Vec<RgbImage>,
    times: Vec<f64>,
    context: Vec<usize>,
}

fn main() {
    let a = args();
    let began = Instant::now();
    let paths = frame_paths(&a.frames);
    assert!(!paths.is_empty(), "no frames in {}", a.frames.display());
    let images: Vec<RgbImage> = paths
        .iter()
        .map(|p| image::open(p).expect("a frame").to_rgb8())
        .collect();
    let times: Vec<f64> = (0..images.len()).map(|i| i as f64 / a.fps).collect();
    let clip = Clip {
        context: spread(images.len(), CONTEXT_FRAMES),
        images,
        times,
    };
    let engine = Engine::load(&a.model, EngineOptions::default()).expect("the model package");
    let inputs: Vec<ContextFrame> = clip
        .context
        .iter()
        .map(|&i| ContextFrame::new(clip.times[i], engine.preprocess(&clip.images[i]).unwrap()))
        .collect();
    let encoding = engine.encode(&inputs).unwrap();
    let (w0, h0) = clip.images[0].dimensions();
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_owned())
        })
        .unwrap_or_default();
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    println!(
        "# {}: {} frames {w0}x{h0} at {} fps, context {:?}; model {}; {cpu}, {cores} cores; loaded and encoded in {:.1} s",
        a.name,
        clip.images.len(),
        a.fps,
        clip.context,
        engine.manifest().name,
        began.elapsed().as_secs_f64()
    );
    let mut csv = a.csv.as_ref().map(|p| {
        std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(p)
            .unwrap()
    });
    println!(
        "clip,run,steps,seconds,gaussians,static,keyframes,frames,crop_psnr,crop_ssim,full_psnr,full_ssim"
    );
    let mut runs: Vec<(Preset, bool)> = a.presets.iter().map(|&p| (p, false)).collect();
    runs.extend(a.random.iter().map(|&p| (p, true)));
    let mut feed_forward_done = false;
    for (preset, random) in runs {
        let mut settings = preset.settings();
        if let Some(s) = a.steps {
            settings.steps = s;
        }
        if let Some(b) = a.budget {
            settings.time_budget_s = Some(b);
        }
        if let Some(r) = a.resolution {
            settings.resolution = r;
        }
        if let Some(k) = a.keyframe_every {
            settings.keyframe_every = k;
        }
        settings.refine_cameras |= a.refine_cameras;
        let result = run(
            &a,
            &engine,
            &encoding,
            &clip,
            &settings,
            random,
            !feed_forward_done,
        );
        feed_forward_done = true;
        for line in result {
            println!("{line}");
            if let Some(f) = csv.as_mut() {
                writeln!(f, "{line}").unwrap();
            }
        }
    }
}

/// One fit at `settings` (from the feed-forward start, or a random one); the lines it prints.
fn run(
    a: &Args,
    engine: &Engine,
    encoding: &c4g_engine::Encoding,
    clip: &Clip,
    settings: &FitSettings,
    random: bool,
    with_feed_forward: bool,
) -> Vec<String> {
    settings.check().unwrap();
    let prepared = Instant::now();
    let used = spread(clip.images.len(), settings.max_frames);
    let context_times: Vec<f64> = clip.context.iter().map(|&i| clip.times[i]).collect();
    let key_times = keyframe_times(&context_times, &clip.times, settings.keyframe_every);
    let sets = engine.decode(encoding, &key_times).unwrap();
    let keyframes = key_times.iter().copied().zip(sets).collect();
    let mut start = FittedScene::new(keyframes).unwrap();
    let frames: Vec<Frame> = used
        .iter()
        .map(|&i| {
            let (w, h, rgb) = working(&clip.images[i], settings.resolution);
            Frame {
                time: clip.times[i],
                rgb,
                camera: camera(w, h),
            }
        })
        .collect();
    let extent = median_depth(&start.sets[0]);
    if random {
        let n = start.len();
        start = random_start(
            &key_times,
            n,
            extent as f32,
            &frames[0].camera,
            settings.seed,
        );
    } else {
        let spacing = (settings.resolution / 48).max(2);
        cover_frame(&mut start, &frames[0], spacing);
    }
    let prepare_s = prepared.elapsed().as_secs_f64();
    let mut options = settings.options(extent);
    if let Some(p) = a.static_pixels {
        options.static_pixels = p;
    }
    if let Some(t) = a.still_threshold {
        options.still_threshold = t;
    }
    if let Some(w) = a.smoothness {
        options.smoothness = w;
    }
    let (scene, report) = fit(&start, &frames, &options, |_| Control::Continue).unwrap();
    let held: Vec<usize> = holdout_frames(frames.len(), settings.holdout_every)
        .into_iter()
        .map(|i| used[i])
        .collect();
    let truths: Vec<(u32, u32, Vec<f32>)> = held
        .iter()
        .map(|&i| working(&clip.images[i], SCORE_SIDE))
        .collect();
    let at = |s: &FittedScene| -> Vec<GaussianSet> {
        held.iter().map(|&i| s.at(clip.times[i]).unwrap()).collect()
    };
    let line = |run: &str, steps: u64, seconds: f64, s: &FittedScene, sc: Score| {
        format!(
            "{},{run},{steps},{seconds:.1},{},{},{},{},{:.2},{:.3},{:.2},{:.3}",
            a.name,
            s.len(),
            s.static_mask.iter().filter(|m| **m).count(),
            s.times.len(),
            frames.len(),
            sc.crop_psnr,
            sc.crop_ssim,
            sc.full_psnr,
            sc.full_ssim
        )
    };
    let mut lines = Vec::new();
    if with_feed_forward {
        let held_times: Vec<f64> = held.iter().map(|&i| clip.times[i]).collect();
        let ff = engine.decode(encoding, &held_times).unwrap();
        let ff_scene = FittedScene::new(held_times.iter().copied().zip(ff.clone()).collect());
        let sc = score(&ff, &truths);
        if let Ok(s) = ff_scene {
            lines.push(line("feed-forward", 0, 0.0, &s, sc));
        }
    }
    let name = if random { "random" } else { "start" };
    if !random || with_feed_forward {
        lines.push(line(
            &format!("{name}:{}", settings_name(settings)),
            0,
            prepare_s,
            &start,
            score(&at(&start), &truths),
        ));
    }
    let run = format!(
        "{}{}",
        if random { "random:" } else { "" },
        settings_name(settings)
    );
    lines.push(line(
        &run,
        report.steps,
        prepare_s + report.seconds,
        &scene,
        score(&at(&scene), &truths),
    ));
    lines.push(format!(
        "# {run}: fit() {:.1} s ({} of {} steps{}), held-out at {} px full frame {:.2} -> {:.2} dB, train {:.2} dB, held out {:?}",
        report.seconds,
        report.steps,
        settings.steps,
        if report.stopped { ", stopped by the budget" } else { "" },
        settings.resolution,
        report.holdout_psnr_before.unwrap_or(f64::NAN),
        report.holdout_psnr_after.unwrap_or(f64::NAN),
        report.train_psnr_after,
        report.holdout_frames
    ));
    lines
}

fn settings_name(s: &FitSettings) -> String {
    Preset::ALL
        .into_iter()
        .find(|p| {
            let d = p.settings();
            d.resolution == s.resolution && d.max_frames == s.max_frames
        })
        .map_or_else(|| format!("custom-{}", s.steps), |p| p.name().to_owned())
}
