//! What the compact 4D stream (`C4GV`, `c4g_formats::c4gv`) costs and saves on real
//! decoded sequences, against the naive packed frames (`C4GS`, 14 values a Gaussian).
//!
//!     source scripts/env.sh && cargo bench -p c4g-engine --bench c4gv
//!
//! A filter argument that does not name `c4gv` skips it. Needs `ORT_DYLIB_PATH`; the `dog` clip
//! also needs `ffmpeg` (its frames are extracted from the MP4), and the real clips need
//! `../shared/data` (`C4G_SHARED` overrides); a clip that cannot be read is left out, with the
//! reason.
//!
//! **Sets.** c4g-tiny (`models/c4g-tiny`, 512 Gaussians) decodes 64 sets evenly over each clip's
//! context span: its three test clips (their own 4 context frames, 0-0.6 s; the three times
//! nearest the ground-truth targets 0.1, 0.3, 0.5 s moved onto them) and the two real clips of
//! `shared/data` (4 context frames: source frames 0, 10, 20 and 30, about 1 s; out of c4g-tiny's
//! domain, but real decoder output all the same).
//!
//! **Bytes per frame** are a stream's bytes over its 64 frames, header and index included:
//! `C4GS` f32 and f16 (`c4gs::encode`), each also deflated whole (what a generic compressor
//! makes of them), and `C4GV` at each position bound, stored and deflated, with the default
//! options otherwise (a keyframe every 16 frames, static detection); and deflated with one
//! keyframe only (K = 64), which is what being able to seek costs.
//!
//! **What quantising costs:** the largest position error over all frames (scene units), and the
//! PSNR of each decoded set's render against the original set's (CPU rasterizer, 64 × 64, the
//! first context camera, clamped to [0, 1]): the worst frame and the pooled error over all 64.
//! For the test clips also the change of PSNR against ground truth at the three targets (the
//! clip's camera at that frame), decoded minus original, mean over targets: the cost that counts.
//! Encode and decode times (deflated, whole stream, per frame) are one run each on whatever
//! machine this is: read them as orders of magnitude.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

// The integration tests' helpers: where the packages and c4g-tiny's test clips are.
#[path = "../tests/common/mod.rs"]
mod common;

use std::io::Write;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

use c4g_engine::{ContextFrame, Engine, EngineOptions};
use c4g_formats::c4gs::{self, Precision};
use c4g_formats::c4gv::{self, EncodeOptions};
use c4g_renderer::{CpuRasterizer, Rasterizer};
use c4g_renderer::{RenderOptions, fidelity};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};
use glam::Mat4;
use serde_json::Value;

/// Sets decoded per clip.
const FRAMES: usize = 64;
/// Render side, pixels.
const SIZE: u32 = 64;
/// Position bounds measured, scene units.
const BOUNDS: [f64; 3] = [1e-2, 1e-3, 1e-4];
/// Source frames of the real clips used as context.
const REAL_CONTEXT: [usize; 4] = [0, 10, 20, 30];

struct Clip {
    name: String,
    /// The decoded sets, evenly over the context span.
    frames: Vec<(f64, GaussianSet)>,
    /// Ground truth (test clips only): per target, its place in `frames`, its camera, its image.
    truth: Vec<(usize, Camera, Vec<f32>)>,
}

fn camera(w2c: Mat4) -> Camera {
    let intrinsics = NormalizedIntrinsics::C4G_DEFAULT.to_pixels(SIZE, SIZE);
    Camera::from_world_to_camera_matrix(intrinsics, w2c).unwrap()
}

fn pose(value: &Value) -> Mat4 {
    let rows: Vec<Vec<f32>> = serde_json::from_value(value.clone()).unwrap();
    Mat4::from_cols_array_2d(&std::array::from_fn(|c| {
        std::array::from_fn(|r| rows[r][c])
    }))
}

fn to_unit(img: &image::RgbImage) -> Vec<f32> {
    img.as_raw().iter().map(|&v| f32::from(v) / 255.0).collect()
}

/// `FRAMES` times evenly over `[lo, hi]`, with the nearest to each of `targets` moved onto it;
/// and where each target landed.
fn times(lo: f64, hi: f64, targets: &[f64]) -> (Vec<f64>, Vec<usize>) {
    let mut times: Vec<f64> = (0..FRAMES)
        .map(|i| lo + (hi - lo) * i as f64 / (FRAMES - 1) as f64)
        .collect();
    let at = targets
        .iter()
        .map(|&t| {
            let k = (0..FRAMES)
                .min_by(|&a, &b| (times[a] - t).abs().total_cmp(&(times[b] - t).abs()))
                .unwrap();
            times[k] = t;
            k
        })
        .collect();
    (times, at)
}

fn decode_span(
    engine: &Engine,
    context: &[ContextFrame],
    targets: &[f64],
) -> (Vec<(f64, GaussianSet)>, Vec<usize>) {
    let encoding = engine.encode(context).unwrap();
    let (lo, hi) = encoding.time_span();
    let (times, at) = times(lo, hi, targets);
    let sets = engine.decode(&encoding, &times).unwrap();
    (times.into_iter().zip(sets).collect(), at)
}

fn test_clip(engine: &Engine, name: &str) -> Clip {
    let dir = common::tiny_dir().join("test-clips").join(name);
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("clip.json")).unwrap()).unwrap();
    let all: Vec<f64> = serde_json::from_value(meta["times"].clone()).unwrap();
    let names: Vec<String> = serde_json::from_value(meta["frames"].clone()).unwrap();
    let targets: Vec<usize> = serde_json::from_value(meta["targets"].clone()).unwrap();
    let clip = common::tiny_clip(engine, name);
    let target_times: Vec<f64> = targets.iter().map(|&f| all[f]).collect();
    let (frames, at) = decode_span(engine, &clip.context, &target_times);
    let truth = targets
        .iter()
        .zip(at)
        .map(|(&f, k)| {
            let image = image::open(dir.join(&names[f])).unwrap().to_rgb8();
            (
                k,
                camera(pose(&meta["world_to_camera_model"][f])),
                to_unit(&image),
            )
        })
        .collect();
    Clip {
        name: name.to_owned(),
        frames,
        truth,
    }
}

/// A real clip from image files (source frame index, path), at `fps`.
fn real_clip(engine: &Engine, name: &str, files: &[(usize, std::path::PathBuf)], fps: f64) -> Clip {
    let context: Vec<ContextFrame> = files
        .iter()
        .map(|(i, path)| {
            let rgb = c4g_engine::preprocess::decode_frame(&std::fs::read(path).unwrap()).unwrap();
            ContextFrame::new(*i as f64 / fps, engine.preprocess(&rgb).unwrap())
        })
        .collect();
    let (frames, _) = decode_span(engine, &context, &[]);
    Clip {
        name: name.to_owned(),
        frames,
        truth: Vec::new(),
    }
}

fn bedroom(engine: &Engine) -> Result<Clip, String> {
    let dir = common::shared_dir().join("data/bedroom/frames");
    let files: Vec<_> = REAL_CONTEXT
        .iter()
        .map(|&i| (i, dir.join(format!("{i:05}.jpg"))))
        .collect();
    if let Some((_, missing)) = files.iter().find(|(_, p)| !p.is_file()) {
        return Err(format!("bedroom left out: {} not found", missing.display()));
    }
    Ok(real_clip(engine, "bedroom (real)", &files, 30.0))
}

fn dog(engine: &Engine, scratch: &Path) -> Result<Clip, String> {
    let video = common::shared_dir().join("data/dog/01_dog.mp4");
    if !video.is_file() {
        return Err(format!("dog left out: {} not found", video.display()));
    }
    let select = REAL_CONTEXT
        .iter()
        .map(|i| format!("eq(n\\,{i})"))
        .collect::<Vec<_>>()
        .join("+");
    let status = Command::new(std::env::var("C4G_FFMPEG").unwrap_or_else(|_| "ffmpeg".into()))
        .args(["-loglevel", "error", "-i"])
        .arg(&video)
        .args(["-vf", &format!("select='{select}'"), "-vsync", "vfr"])
        .arg(scratch.join("dog-%d.png"))
        .status();
    if !status.as_ref().is_ok_and(|s| s.success()) {
        return Err(format!(
            "dog left out: ffmpeg could not extract its frames ({status:?})"
        ));
    }
    let files: Vec<_> = REAL_CONTEXT
        .iter()
        .enumerate()
        .map(|(k, &i)| (i, scratch.join(format!("dog-{}.png", k + 1))))
        .collect();
    Ok(real_clip(engine, "dog (real)", &files, 30000.0 / 1001.0))
}

fn render(rasterizer: &CpuRasterizer, set: &GaussianSet, camera: &Camera) -> Vec<f32> {
    let mut rgb = rasterizer
        .render(set, camera, &RenderOptions::default())
        .unwrap()
        .rgb;
    rgb.iter_mut().for_each(|v| *v = v.clamp(0.0, 1.0));
    rgb
}

fn deflated_len(bytes: &[u8]) -> usize {
    let mut encoder = flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::best());
    encoder.write_all(bytes).unwrap();
    encoder.finish().unwrap().len()
}

fn max_position_error(a: &GaussianSet, b: &GaussianSet) -> f64 {
    a.positions()
        .iter()
        .flatten()
        .zip(b.positions().iter().flatten())
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).abs())
        .fold(0.0, f64::max)
}

fn psnr_of_mse(mse: f64) -> f64 {
    if mse == 0.0 {
        f64::INFINITY
    } else {
        -10.0 * mse.log10()
    }
}

fn db(v: f64) -> String {
    if v.is_infinite() {
        "identical".into()
    } else {
        format!("{v:.1} dB")
    }
}

fn machine() -> String {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let cpu = cpuinfo
        .lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split(':').nth(1))
        .map_or("unknown CPU", str::trim);
    let threads = std::thread::available_parallelism().map_or(0, usize::from);
    let load = std::fs::read_to_string("/proc/loadavg").unwrap_or_default();
    let load: Vec<&str> = load.split_whitespace().take(3).collect();
    format!(
        "{cpu}, {threads} threads; load average {} at the end",
        load.join(" ")
    )
}

/// One row of the C4GV table.
struct Row {
    stored: usize,
    deflated: usize,
    one_keyframe: usize,
    statics: usize,
    max_error: f64,
    worst_psnr: f64,
    pooled_psnr: f64,
    truth_change: Option<f64>,
    encode_ms: f64,
    decode_ms: f64,
}

fn measure(clip: &Clip, bound: f64, rasterizer: &CpuRasterizer, originals: &[Vec<f32>]) -> Row {
    let frames = || clip.frames.iter().map(|(t, s)| (*t, s));
    let options = EncodeOptions {
        position_error: bound,
        ..EncodeOptions::default()
    };
    let started = Instant::now();
    let bytes = c4gv::encode(frames(), &options).unwrap();
    let encode_ms = started.elapsed().as_secs_f64() * 1e3 / FRAMES as f64;
    let started = Instant::now();
    let decoded = c4gv::decode(&bytes).unwrap();
    let decode_ms = started.elapsed().as_secs_f64() * 1e3 / FRAMES as f64;
    let stored = c4gv::encode(
        frames(),
        &EncodeOptions {
            deflate: false,
            ..options
        },
    )
    .unwrap();
    let one_keyframe = c4gv::encode(
        frames(),
        &EncodeOptions {
            keyframe_interval: FRAMES as u32,
            ..options
        },
    )
    .unwrap();
    let mut reader = c4gv::Decoder::new();
    reader.feed(&bytes);
    reader.next_frame().unwrap();
    let statics = reader
        .header()
        .unwrap()
        .static_mask
        .iter()
        .filter(|&&s| s)
        .count();

    let cam = camera(Mat4::IDENTITY);
    let (mut max_error, mut worst, mut sum, mut count) = (0.0f64, f64::INFINITY, 0.0f64, 0usize);
    for (((_, original), (_, back)), reference) in clip.frames.iter().zip(&decoded).zip(originals) {
        max_error = max_error.max(max_position_error(original, back));
        let rgb = render(rasterizer, back, &cam);
        let se: f64 = rgb
            .iter()
            .zip(reference)
            .map(|(a, b)| (f64::from(*a) - f64::from(*b)).powi(2))
            .sum();
        worst = worst.min(psnr_of_mse(se / rgb.len() as f64));
        sum += se;
        count += rgb.len();
    }
    let truth_change = (!clip.truth.is_empty()).then(|| {
        let changes: Vec<f64> = clip
            .truth
            .iter()
            .map(|(k, camera, truth)| {
                let score = |set: &GaussianSet| {
                    fidelity::psnr(&render(rasterizer, set, camera), truth, SIZE, SIZE, None)
                        .unwrap()
                };
                score(&decoded[*k].1) - score(&clip.frames[*k].1)
            })
            .collect();
        changes.iter().sum::<f64>() / changes.len() as f64
    });
    Row {
        stored: stored.len(),
        deflated: bytes.len(),
        one_keyframe: one_keyframe.len(),
        statics,
        max_error,
        worst_psnr: worst,
        pooled_psnr: psnr_of_mse(sum / count as f64),
        truth_change,
        encode_ms,
        decode_ms,
    }
}

fn main() {
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    if !filters.is_empty() && !filters.iter().any(|f| "c4gv".contains(f.as_str())) {
        eprintln!("c4gv: skipped (the filter {filters:?} does not name it)");
        return;
    }
    if std::env::var_os("ORT_DYLIB_PATH").is_none_or(|p| p.is_empty()) {
        eprintln!("c4gv: skipped, ORT_DYLIB_PATH is not set (source scripts/env.sh)");
        return;
    }
    let engine = Engine::load(common::tiny_dir(), EngineOptions::default()).unwrap();
    let scratch = tempfile::tempdir().unwrap();
    let mut clips: Vec<Clip> = common::tiny_clip_names()
        .iter()
        .map(|n| test_clip(&engine, n))
        .collect();
    let mut notes = Vec::new();
    for real in [bedroom(&engine), dog(&engine, scratch.path())] {
        match real {
            Ok(clip) => clips.push(clip),
            Err(note) => notes.push(note),
        }
    }
    let rasterizer = CpuRasterizer::new();
    let cam = camera(Mat4::IDENTITY);

    println!("## Naive frames (bytes per frame, {FRAMES} frames a clip)\n");
    println!("| clip | N | C4GS f32 | C4GS f16 | C4GS f32, deflated | C4GS f16, deflated |");
    println!("|---|---|---|---|---|---|");
    let mut naive = Vec::new();
    for clip in &clips {
        let frames = || clip.frames.iter().map(|(t, s)| (*t, s));
        let f32_bytes = c4gs::encode(frames(), Precision::F32).unwrap();
        let f16_bytes = c4gs::encode(frames(), Precision::F16).unwrap();
        let per = |n: usize| n as f64 / FRAMES as f64;
        println!(
            "| {} | {} | {:.0} | {:.0} | {:.0} | {:.0} |",
            clip.name,
            clip.frames[0].1.len(),
            per(f32_bytes.len()),
            per(f16_bytes.len()),
            per(deflated_len(&f32_bytes)),
            per(deflated_len(&f16_bytes)),
        );
        naive.push(f32_bytes.len());
    }

    println!("\n## C4GV (bytes per frame; % of C4GS f32)\n");
    println!(
        "| clip | position bound | static | stored | deflated | deflated, one keyframe \
         | largest position error | render PSNR vs original: worst frame / pooled | PSNR change vs \
         truth | encode / decode per frame |"
    );
    println!("|---|---|---|---|---|---|---|---|---|---|");
    for (clip, &f32_len) in clips.iter().zip(&naive) {
        let originals: Vec<Vec<f32>> = clip
            .frames
            .iter()
            .map(|(_, s)| render(&rasterizer, s, &cam))
            .collect();
        for bound in BOUNDS {
            let row = measure(clip, bound, &rasterizer, &originals);
            let cell = |n: usize| {
                format!(
                    "{:.0} ({:.1} %)",
                    n as f64 / FRAMES as f64,
                    100.0 * n as f64 / f32_len as f64
                )
            };
            println!(
                "| {} | {bound:e} | {} of {} | {} | **{}** | {} | {:.2e} | {} / {} | {} | {:.2} / {:.2} ms |",
                clip.name,
                row.statics,
                clip.frames[0].1.len(),
                cell(row.stored),
                cell(row.deflated),
                cell(row.one_keyframe),
                row.max_error,
                db(row.worst_psnr),
                db(row.pooled_psnr),
                row.truth_change
                    .map_or("—".into(), |d| format!("{d:+.3} dB")),
                row.encode_ms,
                row.decode_ms,
            );
        }
    }
    for note in notes {
        println!("\n{note}");
    }
    println!("\nMachine: {}", machine());
}
