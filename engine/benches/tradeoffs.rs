//! What the service's speed knobs cost in accuracy, measured on c4g-tiny and its three test clips.
//!
//!     cargo bench -p c4g-engine --bench tradeoffs         # the sweep, about 9 minutes on 2 cores
//!     C4G_TRADEOFFS_QUICK=1 cargo bench -p c4g-engine --bench tradeoffs   # a smoke subset, seconds
//!     $PYTHON -m c4g.bench.tradeoffs_report --results target/tradeoffs.json --out docs
//!
//! A filter argument that does not name `tradeoffs` (`cargo bench -p c4g-engine -- keyframes`)
//! skips it. Results go to `target/tradeoffs.json` (`C4G_TRADEOFFS_OUT` overrides);
//! `c4g.bench.tradeoffs_report` turns them into `docs/tradeoffs.md` and its plot. Needs `ORT_DYLIB_PATH`; the f16 and int8
//! rows also need `PYTHON` (`scripts/env.sh`), which converts the package into a temporary
//! directory with `python -m c4g.package.precision` at the start (without it those rows are skipped, and
//! the JSON says so).
//!
//! **What one setting is.** The knobs: keyframes (exact, every N seconds, a count, adaptive with a
//! position tolerance), pruning (off, or `PruneOptions` with a contribution floor), context frames
//! (2, 3, 4 or 6 of each clip's 7 frames, spread evenly over 0-0.6 s: 4 is the clip's own
//! sampling and the service default), render resolution (64, 128, 256), package precision (f32,
//! f16, int8) and wire precision (the C4GS payload's f32 or f16: the sets are packed and unpacked
//! before they are rendered, so f16's rounding is in the numbers). The baseline, `exact`, is f32,
//! 4 context frames, exact decodes, no pruning, 64 px, f32 wire; every other setting changes one
//! knob from it, or several (the preset candidates). Not the cross product: it would take hours.
//!
//! **Per clip and setting:** 64 output times evenly over the context span (0-0.6 s), the three
//! nearest the ground-truth target times (0.1, 0.3, 0.5 s) moved onto them. Timed, per clip the
//! best of the rounds (at least `MIN_ROUNDS`, more while `BUDGET_S` allows; each round times
//! every setting once, in its own shuffled order, so that a burst of load from elsewhere costs a
//! setting one round, not all its runs): producing the 64 sets (decode, or keyframe decodes and
//! interpolation, then `GaussianSet::select` when pruning), the C4GS round trip, and rendering each set on the CPU
//! rasterizer at the clip's camera at that time (poses interpolated between the clip's frames).
//! Untimed, once per clip: encoding, and the pruning analysis (`SceneAnalysis::measure`) on exact
//! sets at `ANALYSIS_TIMES` times evenly over the span, rendered at the setting's resolution from
//! every context frame's camera and a ring of 4 nearby novel views (an orbit about the point 2
//! units ahead of the first context camera at -15, -7.5, +7.5 and +15 degrees). The clips' novel
//! camera (moved 0.15, -0.05, 0.1 and turned 6 degrees) is not in the ring, so its scores say
//! whether pruning holds away from the measured views.
//!
//! **Quality.** Against ground truth as `tests/tiny_quality.rs` scores it (renders clamped to
//! [0, 1]; at 128 and 256 px box-downsampled to the ground truth's 64 px): PSNR and SSIM at the
//! three targets from the clip's camera ("interpolated") and from the novel camera, mean over
//! images. Against exact: the same renders (all 64 path frames and the 3 novel views) against the
//! baseline's at the same resolution, PSNR of the pooled squared error (`null` when identical),
//! the worst frame's PSNR, and SSIM averaged over every 4th path frame and the novel views.
//!
//! **Memory** is the process's peak resident set (`VmHWM`, reset by writing 5 to
//! `/proc/self/clear_refs` before each setting): it includes every loaded engine and the
//! harness's own buffers (the exact renders kept to compare with), so read differences between
//! rows, with `peak_rise_mib` (peak minus the resident set when the setting started).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

// The integration tests' helpers: where the packages and c4g-tiny's test clips are.
#[path = "../tests/common/mod.rs"]
mod common;

use common::load_average;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use c4g_analysis::pruning::{PruneOptions, SceneAnalysis};
use c4g_engine::{ContextFrame, Encoding, Engine, EngineOptions, KeyframeTrack, Keyframes};
use c4g_formats::c4gs::{self, Precision as Wire};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions, fidelity};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics, Trajectory, trajectory};
use glam::Mat4;
use image::RgbImage;
use serde_json::{Value, json};

/// Output times per clip.
const OUTPUT_FRAMES: usize = 64;
/// Exact decodes the pruning analysis samples per clip.
const ANALYSIS_TIMES: usize = 5;
/// Ground truth's resolution (the clips' frames).
const TRUTH_SIZE: u32 = 64;
/// Timed runs of every setting (the first also measures quality) at least; the quick mode makes
/// one.
const MIN_ROUNDS: usize = 3;
/// More rounds are run while the sweep's time (`C4G_TRADEOFFS_BUDGET_S` overrides) leaves room
/// for one like the last: on a quiet machine about 6 in all, on a busy one the minimum.
const BUDGET_S: f64 = 540.0;
/// Rounds at most, however quiet the machine.
const MAX_ROUNDS: usize = 8;
/// Every how many path frames SSIM against exact is computed.
const SSIM_STRIDE: usize = 4;

// ---------------------------------------------------------------------------------------------
// Settings

#[derive(Debug, Clone, PartialEq)]
struct Setting {
    name: String,
    /// Which knob the row varies from the baseline ("baseline", "keyframes", ..., "combination").
    knob: &'static str,
    keyframes: Keyframes,
    /// Contribution floor in pixels; `None`: no pruning.
    prune: Option<f32>,
    context: usize,
    resolution: u32,
    precision: &'static str,
    wire: Wire,
}

impl Setting {
    fn exact() -> Self {
        Self {
            name: "exact".into(),
            knob: "baseline",
            keyframes: Keyframes::Exact,
            prune: None,
            context: 4,
            resolution: 64,
            precision: "f32",
            wire: Wire::F32,
        }
    }

    fn keyframes(mut self, k: Keyframes) -> Self {
        self.keyframes = k;
        self.named("keyframes")
    }
    fn prune(mut self, floor: f32) -> Self {
        self.prune = Some(floor);
        self.named("pruning")
    }
    fn context(mut self, t: usize) -> Self {
        self.context = t;
        self.named("context frames")
    }
    fn resolution(mut self, r: u32) -> Self {
        self.resolution = r;
        self.named("resolution")
    }
    fn precision(mut self, p: &'static str) -> Self {
        self.precision = p;
        self.named("precision")
    }
    fn wire(mut self, w: Wire) -> Self {
        self.wire = w;
        self.named("wire")
    }

    /// Names the setting by what differs from the baseline; more than one difference is a
    /// combination.
    fn named(mut self, knob: &'static str) -> Self {
        let base = Self::exact();
        let mut parts = Vec::new();
        if self.keyframes != base.keyframes {
            parts.push(keyframes_label(&self.keyframes));
        }
        if let Some(floor) = self.prune {
            parts.push(format!("prune {floor} px"));
        }
        if self.context != base.context {
            parts.push(format!("T={}", self.context));
        }
        if self.precision != base.precision {
            parts.push(format!("{} package", self.precision));
        }
        if self.wire != base.wire {
            parts.push(format!("{} wire", self.wire));
        }
        if self.resolution != base.resolution {
            parts.push(format!("{} px", self.resolution));
        }
        self.knob = if parts.len() > 1 { "combination" } else { knob };
        self.name = if parts.is_empty() {
            "exact".into()
        } else {
            parts.join(" + ")
        };
        self
    }
}

fn keyframes_label(k: &Keyframes) -> String {
    match *k {
        Keyframes::Exact => "exact".into(),
        Keyframes::Every { seconds } => format!("every {seconds} s"),
        Keyframes::Count { n } => format!("count {n}"),
        Keyframes::Adaptive { tolerance, .. } => format!("adaptive {tolerance}"),
    }
}

fn keyframes_json(k: &Keyframes) -> Value {
    match *k {
        Keyframes::Exact => json!({"mode": "exact"}),
        Keyframes::Every { seconds } => json!({"mode": "every", "seconds": seconds}),
        Keyframes::Count { n } => json!({"mode": "count", "n": n}),
        Keyframes::Adaptive {
            tolerance,
            color_tolerance,
            max_keyframes,
            min_interval,
        } => json!({"mode": "adaptive", "tolerance": tolerance,
            "color_tolerance": color_tolerance, "max_keyframes": max_keyframes,
            "min_interval": min_interval}),
    }
}

fn adaptive(tolerance: f64) -> Keyframes {
    Keyframes::adaptive(tolerance, Keyframes::DEFAULT_MAX_KEYFRAMES)
}

/// The sweep: one knob at a time from the baseline, then combinations that look like presets.
/// Grouped by package precision.
fn sweep(quick: bool) -> Vec<Setting> {
    let base = Setting::exact;
    if quick {
        return vec![
            base(),
            base().keyframes(Keyframes::Count { n: 8 }),
            base().keyframes(adaptive(0.01)).prune(0.5).wire(Wire::F16),
            base().precision("int8"),
        ];
    }
    let every = |seconds| Keyframes::Every { seconds };
    let count = |n| Keyframes::Count { n };
    let mut s = vec![base()];
    for k in [
        every(0.1),
        every(0.2),
        every(0.3),
        count(2),
        count(4),
        count(8),
        count(16),
        adaptive(0.02),
        adaptive(0.01),
        adaptive(0.005),
        adaptive(0.002),
    ] {
        s.push(base().keyframes(k));
    }
    s.push(base().prune(0.5));
    s.push(base().prune(2.0));
    for t in [2, 3, 6] {
        s.push(base().context(t));
    }
    s.push(base().wire(Wire::F16));
    // Preset candidates at 64 px, f32 package: finer to coarser, without pruning and with it.
    s.push(base().keyframes(adaptive(0.01)).wire(Wire::F16));
    s.push(base().keyframes(every(0.2)).wire(Wire::F16));
    s.push(base().keyframes(every(0.3)).wire(Wire::F16));
    s.push(base().keyframes(adaptive(0.005)).prune(0.5));
    s.push(base().keyframes(adaptive(0.002)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(adaptive(0.005)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(adaptive(0.01)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(adaptive(0.02)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(count(16)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(every(0.1)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(every(0.2)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(every(0.3)).prune(0.5).wire(Wire::F16));
    s.push(base().keyframes(every(0.2)).prune(2.0).wire(Wire::F16));
    s.push(base().keyframes(count(2)).prune(0.5).wire(Wire::F16));
    // Resolution, alone and with the candidates (render cost grows with pixels).
    for r in [128, 256] {
        s.push(base().resolution(r));
        s.push(base().resolution(r).prune(0.5));
        s.push(
            base()
                .resolution(r)
                .keyframes(adaptive(0.005))
                .prune(0.5)
                .wire(Wire::F16),
        );
        s.push(
            base()
                .resolution(r)
                .keyframes(every(0.2))
                .prune(0.5)
                .wire(Wire::F16),
        );
    }
    // Lower-precision packages, alone and with the candidates.
    for p in ["f16", "int8"] {
        s.push(base().precision(p));
    }
    s.push(
        base()
            .precision("int8")
            .keyframes(adaptive(0.005))
            .prune(0.5)
            .wire(Wire::F16),
    );
    s.push(
        base()
            .precision("int8")
            .keyframes(every(0.2))
            .prune(0.5)
            .wire(Wire::F16),
    );
    s.push(
        base()
            .precision("int8")
            .keyframes(every(0.3))
            .prune(0.5)
            .wire(Wire::F16),
    );
    s.push(
        base()
            .precision("int8")
            .keyframes(count(2))
            .prune(0.5)
            .wire(Wire::F16),
    );
    s.sort_by_key(|x| match x.precision {
        "f32" => 0,
        "f16" => 1,
        _ => 2,
    });
    s
}

// ---------------------------------------------------------------------------------------------
// Clips, cameras, images

struct Clip {
    name: String,
    /// Every frame's time, seconds.
    times: Vec<f64>,
    frames: Vec<RgbImage>,
    /// Every frame preprocessed for the package (the same input for every precision).
    pixels: Vec<Vec<f32>>,
    /// World-to-camera of every frame, model units.
    w2c: Vec<Mat4>,
    /// Frame indices of the ground-truth targets.
    targets: Vec<usize>,
    /// Novel camera and its ground truth, per target.
    novel_w2c: Vec<Mat4>,
    novel: Vec<RgbImage>,
}

fn pose(value: &Value) -> Mat4 {
    let rows: Vec<Vec<f32>> = serde_json::from_value(value.clone()).unwrap();
    let mut cols = [[0.0f32; 4]; 4];
    for (r, row) in rows.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            cols[c][r] = *v;
        }
    }
    Mat4::from_cols_array_2d(&cols)
}

fn load_rgb(path: &Path) -> RgbImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgb8()
}

fn load_clip(engine: &Engine, name: &str) -> Clip {
    let dir = common::tiny_dir().join("test-clips").join(name);
    let meta: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("clip.json")).unwrap()).unwrap();
    let times: Vec<f64> = serde_json::from_value(meta["times"].clone()).unwrap();
    let names: Vec<String> = serde_json::from_value(meta["frames"].clone()).unwrap();
    let targets: Vec<usize> = serde_json::from_value(meta["targets"].clone()).unwrap();
    let frames: Vec<RgbImage> = names.iter().map(|n| load_rgb(&dir.join(n))).collect();
    let pixels = frames
        .iter()
        .map(|f| engine.preprocess(f).unwrap())
        .collect();
    let w2c = (0..times.len())
        .map(|i| pose(&meta["world_to_camera_model"][i]))
        .collect();
    let novel_w2c = (0..targets.len())
        .map(|k| pose(&meta["novel_world_to_camera_model"][k]))
        .collect();
    let novel = (0..targets.len())
        .map(|k| load_rgb(&dir.join(format!("novel-{k:02}.png"))))
        .collect();
    Clip {
        name: name.to_owned(),
        times,
        frames,
        pixels,
        w2c,
        targets,
        novel_w2c,
        novel,
    }
}

/// `count` frame indices spread evenly over `frames` frames, both ends included: for 7 frames,
/// T = 2: 0 6; 3: 0 3 6; 4: 0 2 4 6 (the clips' own); 6: 0 1 2 4 5 6.
fn context_indices(count: usize, frames: usize) -> Vec<usize> {
    (0..count)
        .map(|i| ((i * (frames - 1)) as f64 / (count - 1) as f64).round() as usize)
        .collect()
}

impl Clip {
    fn context(&self, count: usize) -> Vec<ContextFrame> {
        context_indices(count, self.times.len())
            .into_iter()
            .map(|i| ContextFrame::new(self.times[i], self.pixels[i].clone()))
            .collect()
    }

    /// 64 times evenly over the span, with the nearest to each target moved onto it; and where
    /// each target sits in them.
    fn output_times(&self) -> (Vec<f64>, Vec<usize>) {
        let (lo, hi) = (self.times[0], *self.times.last().unwrap());
        let mut times: Vec<f64> = (0..OUTPUT_FRAMES)
            .map(|i| lo + (hi - lo) * i as f64 / (OUTPUT_FRAMES - 1) as f64)
            .collect();
        let at = self
            .targets
            .iter()
            .map(|&f| {
                let t = self.times[f];
                let (k, _) = times
                    .iter()
                    .enumerate()
                    .min_by(|a, b| (a.1 - t).abs().total_cmp(&(b.1 - t).abs()))
                    .unwrap();
                times[k] = t;
                k
            })
            .collect();
        (times, at)
    }

    fn camera(w2c: Mat4, size: u32) -> Camera {
        let intrinsics = NormalizedIntrinsics::C4G_DEFAULT.to_pixels(size, size);
        Camera::from_world_to_camera_matrix(intrinsics, w2c).unwrap()
    }

    /// The clip's camera at `t`: a frame's own at its time, else interpolated between the two
    /// frames around it.
    fn camera_at(&self, t: f64, size: u32) -> Camera {
        if let Some(i) = self.times.iter().position(|&x| (x - t).abs() < 1e-9) {
            return Self::camera(self.w2c[i], size);
        }
        let k = self
            .times
            .partition_point(|&x| x < t)
            .clamp(1, self.times.len() - 1)
            - 1;
        let s = ((t - self.times[k]) / (self.times[k + 1] - self.times[k])) as f32;
        let (a, b) = (
            Self::camera(self.w2c[k], size),
            Self::camera(self.w2c[k + 1], size),
        );
        trajectory::interpolate(&a, &b, s.clamp(0.0, 1.0)).unwrap()
    }

    /// The pruning analysis's views: every context frame's camera and the ring.
    fn analysis_cameras(&self, context: usize, size: u32) -> Vec<Camera> {
        let indices = context_indices(context, self.times.len());
        let mut cameras: Vec<Camera> = indices
            .iter()
            .map(|&i| Self::camera(self.w2c[i], size))
            .collect();
        let ring = Trajectory::Orbit {
            depth: 2.0,
            angle_degrees: 30.0,
            radius: None,
        }
        .cameras(&cameras[0], 5)
        .unwrap();
        // -15, -7.5, (0: the context camera itself), +7.5, +15 degrees.
        cameras.extend(
            ring.into_iter()
                .enumerate()
                .filter(|(i, _)| *i != 2)
                .map(|(_, c)| c),
        );
        cameras
    }
}

fn to_unit(img: &RgbImage) -> Vec<f32> {
    img.as_raw().iter().map(|&v| f32::from(v) / 255.0).collect()
}

fn render_rgb(rasterizer: &CpuRasterizer, set: &GaussianSet, camera: &Camera) -> Vec<f32> {
    let mut rgb = rasterizer
        .render(set, camera, &RenderOptions::default())
        .unwrap()
        .rgb;
    for v in &mut rgb {
        *v = v.clamp(0.0, 1.0);
    }
    rgb
}

/// `rgb` (size × size) box-averaged down to the ground truth's resolution.
fn downsample(rgb: &[f32], size: u32) -> Vec<f32> {
    let f = (size / TRUTH_SIZE) as usize;
    if f <= 1 {
        return rgb.to_vec();
    }
    let (w, n) = (size as usize, TRUTH_SIZE as usize);
    let mut out = vec![0.0f32; n * n * 3];
    for y in 0..n {
        for x in 0..n {
            for c in 0..3 {
                let mut sum = 0.0;
                for dy in 0..f {
                    for dx in 0..f {
                        sum += rgb[((y * f + dy) * w + x * f + dx) * 3 + c];
                    }
                }
                out[(y * n + x) * 3 + c] = sum / (f * f) as f32;
            }
        }
    }
    out
}

fn squared_error(a: &[f32], b: &[f32]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum()
}

fn psnr_of_mse(mse: f64) -> Option<f64> {
    (mse > 0.0).then(|| -10.0 * mse.log10())
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len().max(1) as f64
}

// ---------------------------------------------------------------------------------------------
// Machine, memory

fn machine() -> Value {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let cpu = cpuinfo
        .lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split(':').nth(1))
        .map_or("unknown CPU".to_owned(), |s| s.trim().to_owned());
    let mem_gib = std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .next()?
                .split_whitespace()
                .nth(1)?
                .parse::<f64>()
                .ok()
        })
        .map_or(0.0, |kib| kib / 1024.0 / 1024.0);
    let os = std::fs::read_to_string("/etc/os-release")
        .ok()
        .and_then(|s| {
            s.lines()
                .find_map(|l| l.strip_prefix("PRETTY_NAME="))
                .map(|v| v.trim_matches('"').to_owned())
        })
        .unwrap_or_default();
    let ort = std::env::var("ORT_DYLIB_PATH")
        .ok()
        .and_then(|p| {
            Path::new(&p)
                .file_name()
                .map(|f| f.to_string_lossy().into_owned())
        })
        .unwrap_or_default();
    json!({
        "cpu": cpu,
        "threads": std::thread::available_parallelism().map_or(0, usize::from),
        "memory_gib": (mem_gib * 10.0).round() / 10.0,
        "os": os,
        "onnxruntime": ort,
        "execution": "CPU only: ONNX Runtime's CPU execution provider, the CPU rasterizer",
    })
}

/// Resets the process's peak resident set to the current one (Linux ≥ 4.0).
fn reset_peak() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// A `/proc/self/status` entry in MiB (`VmHWM`, `VmRSS`).
fn status_mib(key: &str) -> Option<f64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(key))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

// ---------------------------------------------------------------------------------------------
// Packages

/// Packages by precision: the committed f32 one, and f16 / int8 converted into `dir` by
/// `python -m c4g.package.precision`. A precision that cannot be made is left out with the reason.
fn packages(dir: &Path, wanted: &[&'static str]) -> (HashMap<&'static str, PathBuf>, Vec<String>) {
    let mut out = HashMap::from([("f32", common::tiny_dir())]);
    let mut notes = Vec::new();
    let python = std::env::var_os("PYTHON").filter(|p| !p.is_empty());
    for &p in wanted.iter().filter(|&&p| p != "f32") {
        let Some(python) = &python else {
            notes.push(format!(
                "{p} rows skipped: PYTHON is not set (source scripts/env.sh)"
            ));
            continue;
        };
        let target = dir.join(format!("c4g-tiny-{p}"));
        let status = Command::new(python)
            .args(["-m", "c4g.package.precision", "--package"])
            .arg(common::tiny_dir())
            .args(["--precision", p, "--out"])
            .arg(&target)
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::null())
            .status();
        match status {
            Ok(s) if s.success() => {
                out.insert(p, target);
            }
            other => notes.push(format!(
                "{p} rows skipped: python -m c4g.package.precision failed ({other:?})"
            )),
        }
    }
    (out, notes)
}

// ---------------------------------------------------------------------------------------------
// Measuring

/// The 64 sets of one clip under a setting's keyframes and pruning (`keep`).
fn produce(
    engine: &Engine,
    encoding: &Encoding,
    times: &[f64],
    keyframes: &Keyframes,
    keep: Option<&[bool]>,
) -> (Vec<GaussianSet>, usize, usize) {
    match (keyframes, keep) {
        (Keyframes::Exact, _) => {
            let sets = engine.decode(encoding, times).unwrap();
            let sets = match keep {
                Some(keep) => sets.iter().map(|s| s.select(keep).unwrap()).collect(),
                None => sets,
            };
            let runs = times
                .len()
                .div_ceil(engine.decode_batch_size(encoding.frame_count()));
            (sets, times.len(), runs)
        }
        (_, None) => {
            let (sets, stats) = engine.decode_keyframed(encoding, times, keyframes).unwrap();
            (sets, stats.exact_decodes, stats.decoder_runs)
        }
        (_, Some(keep)) => {
            // Prune the keyframes, then interpolate: per Gaussian, so the same sets as
            // interpolating first and pruning after, for fewer Gaussians' work.
            let (track, stats) = engine.keyframe_track(encoding, times, keyframes).unwrap();
            let pruned = track
                .times()
                .iter()
                .zip(track.sets())
                .map(|(&t, s)| (t, s.select(keep).unwrap()))
                .collect();
            let track = KeyframeTrack::with_breaks(pruned, encoding.times()).unwrap();
            let sets = times.iter().map(|&t| track.at(t).unwrap()).collect();
            (sets, stats.exact_decodes, stats.decoder_runs)
        }
    }
}

/// The baseline's renders of one clip at one resolution: the 64 path frames and the novel views.
struct Reference {
    path: Vec<Vec<f32>>,
    novel: Vec<Vec<f32>>,
}

struct Harness {
    clips: Vec<Clip>,
    rasterizer: CpuRasterizer,
    encodings: HashMap<(&'static str, usize, usize), (Encoding, f64)>,
    references: HashMap<(usize, u32), Reference>,
}

impl Harness {
    fn encoding(
        &mut self,
        engine: &Engine,
        precision: &'static str,
        t: usize,
        clip: usize,
    ) -> (Encoding, f64) {
        let entry = self
            .encodings
            .entry((precision, t, clip))
            .or_insert_with(|| {
                let context = self.clips[clip].context(t);
                let start = Instant::now();
                let encoding = engine.encode(&context).unwrap();
                (encoding, start.elapsed().as_secs_f64() * 1e3)
            });
        (entry.0.clone(), entry.1)
    }

    fn reference(&mut self, f32_engine: &Engine, clip: usize, size: u32) -> &Reference {
        if !self.references.contains_key(&(clip, size)) {
            let (encoding, _) = self.encoding(f32_engine, "f32", 4, clip);
            let c = &self.clips[clip];
            let (times, at) = c.output_times();
            let sets = f32_engine.decode(&encoding, &times).unwrap();
            let path = sets
                .iter()
                .zip(&times)
                .map(|(s, &t)| render_rgb(&self.rasterizer, s, &c.camera_at(t, size)))
                .collect();
            let novel = at
                .iter()
                .zip(&c.novel_w2c)
                .map(|(&k, &w2c)| render_rgb(&self.rasterizer, &sets[k], &Clip::camera(w2c, size)))
                .collect();
            self.references
                .insert((clip, size), Reference { path, novel });
        }
        &self.references[&(clip, size)]
    }

    /// One timed run of `s` on clip `c`: produce the sets, send them through C4GS, render them.
    fn time_once(
        &self,
        s: &Setting,
        engine: &Engine,
        c: usize,
        encoding: &Encoding,
        keep: Option<&[bool]>,
    ) -> Run {
        let clip = &self.clips[c];
        let (times, _) = clip.output_times();
        let cameras: Vec<Camera> = times
            .iter()
            .map(|&t| clip.camera_at(t, s.resolution))
            .collect();
        let t0 = Instant::now();
        let (sets, decodes, runs) = produce(engine, encoding, &times, &s.keyframes, keep);
        let t1 = Instant::now();
        let payload = c4gs::encode(times.iter().copied().zip(&sets), s.wire).unwrap();
        let received: Vec<GaussianSet> = c4gs::decode(&payload)
            .unwrap()
            .into_iter()
            .map(|(_, set)| set)
            .collect();
        let t2 = Instant::now();
        let renders: Vec<Vec<f32>> = received
            .iter()
            .zip(&cameras)
            .map(|(set, cam)| render_rgb(&self.rasterizer, set, cam))
            .collect();
        let t3 = Instant::now();
        Run {
            seconds: [
                (t1 - t0).as_secs_f64(),
                (t2 - t1).as_secs_f64(),
                (t3 - t2).as_secs_f64(),
            ],
            received,
            renders,
            decodes,
            runs,
        }
    }

    /// The first round of a setting: its pruning analysis, one timed run per clip, and its quality
    /// (deterministic, so measured once) and memory.
    fn first(&mut self, s: &Setting, engine: &Engine, f32_engine: &Engine) -> Prepared {
        let size = s.resolution;
        // References first: their renders are the harness's, not the setting's.
        for c in 0..self.clips.len() {
            self.reference(f32_engine, c, size);
        }
        let peak_reset = reset_peak();
        let rss_start = status_mib("VmRSS:");
        let (mut encodings, mut keeps, mut best) = (Vec::new(), Vec::new(), Vec::new());
        let (mut encode_ms, mut analysis_ms) = (Vec::new(), Vec::new());
        let (mut decodes, mut runs, mut kept) = (Vec::new(), Vec::new(), Vec::new());
        let mut dropped_bound = Vec::new();
        let (mut bytes32, mut bytes16) = (Vec::new(), Vec::new());
        let (mut gt_psnr_i, mut gt_ssim_i, mut gt_psnr_n, mut gt_ssim_n) =
            (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        let (mut sq_err, mut values) = (0.0f64, 0usize);
        let mut worst_frame = f64::INFINITY;
        let mut ssim_exact = Vec::new();
        let mut per_clip = Vec::new();
        for c in 0..self.clips.len() {
            let (encoding, encode) = self.encoding(engine, s.precision, s.context, c);
            encode_ms.push(encode);
            let clip = &self.clips[c];
            let (_, at) = clip.output_times();
            let keep = s.prune.map(|floor| {
                let start = Instant::now();
                let (lo, hi) = encoding.time_span();
                let sample: Vec<f64> = (0..ANALYSIS_TIMES)
                    .map(|i| lo + (hi - lo) * i as f64 / (ANALYSIS_TIMES - 1) as f64)
                    .collect();
                let sets = engine.decode(&encoding, &sample).unwrap();
                let views = clip.analysis_cameras(s.context, size);
                let analysis = SceneAnalysis::measure(
                    &sets,
                    &views,
                    &self.rasterizer,
                    &RenderOptions::default(),
                )
                .unwrap();
                let options = PruneOptions {
                    contribution_floor: floor,
                    ..PruneOptions::default()
                };
                analysis_ms.push(start.elapsed().as_secs_f64() * 1e3);
                dropped_bound.push(f64::from(analysis.dropped_contribution(&options)));
                analysis.keep(&options)
            });
            let run = self.time_once(s, engine, c, &encoding, keep.as_deref());
            best.push(run.seconds);
            decodes.push(run.decodes as f64);
            runs.push(run.runs as f64);
            let n = run.received[0].len();
            kept.push(n as f64);
            let per_frame = |w: Wire| (8 + n * 14 * w.value_bytes()) as f64;
            bytes32.push(per_frame(Wire::F32));
            bytes16.push(per_frame(Wire::F16));
            // Quality against ground truth.
            let novel: Vec<Vec<f32>> = at
                .iter()
                .zip(&clip.novel_w2c)
                .map(|(&k, &w2c)| {
                    render_rgb(&self.rasterizer, &run.received[k], &Clip::camera(w2c, size))
                })
                .collect();
            let mut clip_psnr = Vec::new();
            for (j, (&k, &frame)) in at.iter().zip(&clip.targets).enumerate() {
                for (render, truth, psnrs, ssims) in [
                    (
                        &run.renders[k],
                        &clip.frames[frame],
                        &mut gt_psnr_i,
                        &mut gt_ssim_i,
                    ),
                    (&novel[j], &clip.novel[j], &mut gt_psnr_n, &mut gt_ssim_n),
                ] {
                    let ours = downsample(render, size);
                    let truth = to_unit(truth);
                    let p = fidelity::psnr(&ours, &truth, TRUTH_SIZE, TRUTH_SIZE, None).unwrap();
                    psnrs.push(p);
                    clip_psnr.push(p);
                    ssims
                        .push(fidelity::ssim(&ours, &truth, TRUTH_SIZE, TRUTH_SIZE, None).unwrap());
                }
            }
            // Quality against exact.
            let reference = &self.references[&(c, size)];
            let pairs = run
                .renders
                .iter()
                .zip(&reference.path)
                .chain(novel.iter().zip(&reference.novel));
            for (i, (ours, exact)) in pairs.enumerate() {
                let e = squared_error(ours, exact);
                sq_err += e;
                values += ours.len();
                if let Some(p) = psnr_of_mse(e / ours.len() as f64) {
                    worst_frame = worst_frame.min(p);
                }
                if i % SSIM_STRIDE == 0 || i >= OUTPUT_FRAMES {
                    ssim_exact.push(fidelity::ssim(ours, exact, size, size, None).unwrap());
                }
            }
            per_clip.push(json!({
                "clip": clip.name,
                "exact_decodes": run.decodes,
                "gaussians": n,
                "gt_psnr": mean(&clip_psnr),
            }));
            encodings.push(encoding);
            keeps.push(keep);
        }
        let peak = status_mib("VmHWM:");
        let row = json!({
            "name": s.name,
            "knob": s.knob,
            "keyframes": keyframes_json(&s.keyframes),
            "prune": s.prune.map(|floor| json!({
                "opacity_floor": PruneOptions::default().opacity_floor,
                "contribution_floor": floor,
            })),
            "context_frames": s.context,
            "resolution": size,
            "precision": s.precision,
            "wire": s.wire.as_str(),
            "encode_ms_per_clip": mean(&encode_ms),
            "analysis_ms_per_clip": (!analysis_ms.is_empty()).then(|| mean(&analysis_ms)),
            "exact_decodes_per_clip": mean(&decodes),
            "decoder_runs_per_clip": mean(&runs),
            "gaussians": mean(&kept),
            "dropped_contribution_px": (!dropped_bound.is_empty()).then(|| mean(&dropped_bound)),
            "bytes_per_frame_f32": mean(&bytes32),
            "bytes_per_frame_f16": mean(&bytes16),
            "peak_rss_mib": peak,
            "peak_rise_mib": peak.zip(rss_start).map(|(p, r)| p - r),
            "peak_reset": peak_reset,
            "gt": {
                "psnr_interpolated": mean(&gt_psnr_i),
                "ssim_interpolated": mean(&gt_ssim_i),
                "psnr_novel": mean(&gt_psnr_n),
                "ssim_novel": mean(&gt_ssim_n),
                "psnr": mean(&[gt_psnr_i.clone(), gt_psnr_n.clone()].concat()),
                "ssim": mean(&[gt_ssim_i.clone(), gt_ssim_n.clone()].concat()),
            },
            "vs_exact": {
                "psnr": psnr_of_mse(sq_err / values as f64),
                "psnr_worst_frame": worst_frame.is_finite().then_some(worst_frame),
                "ssim": mean(&ssim_exact),
            },
            "clips": per_clip,
        });
        let mut prepared = Prepared {
            encodings,
            keeps,
            best: best.clone(),
            rounds: Vec::new(),
            row,
        };
        prepared.record(&best);
        prepared
    }

    /// A later round of a setting: one more timed run per clip.
    fn again(&self, s: &Setting, engine: &Engine, prepared: &mut Prepared) {
        let seconds: Vec<[f64; 3]> = (0..self.clips.len())
            .map(|c| {
                self.time_once(
                    s,
                    engine,
                    c,
                    &prepared.encodings[c],
                    prepared.keeps[c].as_deref(),
                )
                .seconds
            })
            .collect();
        prepared.record(&seconds);
    }
}

/// One timed run on one clip.
struct Run {
    /// Producing the sets, the C4GS round trip, rendering.
    seconds: [f64; 3],
    received: Vec<GaussianSet>,
    renders: Vec<Vec<f32>>,
    decodes: usize,
    runs: usize,
}

/// A setting between rounds: per clip its encoding, pruning mask and best times so far; the
/// total of each round (produce + render, all clips); the row measured in the first.
struct Prepared {
    encodings: Vec<Encoding>,
    keeps: Vec<Option<Vec<bool>>>,
    best: Vec<[f64; 3]>,
    rounds: Vec<f64>,
    row: Value,
}

impl Prepared {
    fn record(&mut self, seconds: &[[f64; 3]]) {
        for (best, run) in self.best.iter_mut().zip(seconds) {
            for k in 0..3 {
                best[k] = best[k].min(run[k]);
            }
        }
        self.rounds
            .push(seconds.iter().map(|s| s[0] + s[2]).sum::<f64>());
    }

    /// The row with its times: per clip the best over the rounds, summed over clips.
    fn finish(mut self, clips: usize) -> Value {
        let frames = (OUTPUT_FRAMES * clips) as f64;
        let total = |k: usize| self.best.iter().map(|b| b[k]).sum::<f64>();
        let (produce, wire, render) = (total(0), total(1), total(2));
        let ms = |s: f64| s * 1e3 / frames;
        let analysis_s =
            self.row["analysis_ms_per_clip"].as_f64().unwrap_or(0.0) * clips as f64 / 1e3;
        let timing = json!({
            "ms_per_frame": ms(produce + render),
            "decode_ms_per_frame": ms(produce),
            "render_ms_per_frame": ms(render),
            "decode_share": produce / (produce + render),
            "wire_ms_per_frame": ms(wire),
            "sets_per_s": frames / produce,
            "sets_per_s_with_analysis": frames / (produce + analysis_s),
            "ms_per_frame_rounds": self.rounds.iter().map(|&s| ms(s)).collect::<Vec<_>>(),
        });
        for (k, v) in timing.as_object().unwrap() {
            self.row[k] = v.clone();
        }
        for (clip, best) in self.row["clips"]
            .as_array_mut()
            .unwrap()
            .iter_mut()
            .zip(&self.best)
        {
            clip["produce_ms"] = json!(best[0] * 1e3);
            clip["render_ms"] = json!(best[2] * 1e3);
        }
        self.row
    }
}

/// `0..n` in an order fixed by `seed` (Fisher-Yates on a 64-bit LCG: reproducible, no dependency).
fn shuffled(n: usize, seed: u64) -> Vec<usize> {
    let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    let mut order: Vec<usize> = (0..n).collect();
    for i in (1..n).rev() {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        order.swap(i, ((state >> 33) % (i as u64 + 1)) as usize);
    }
    order
}

fn fmt_opt(v: &Value) -> String {
    v.as_f64().map_or("identical".into(), |x| format!("{x:.2}"))
}

fn main() {
    // `cargo bench -p c4g-engine -- keyframes` passes its filter to every bench of the crate: like
    // criterion, run only when no filter is given or one names this harness.
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    if !filters.is_empty() && !filters.iter().any(|f| "tradeoffs".contains(f.as_str())) {
        eprintln!("tradeoffs: skipped (the filter {filters:?} does not name it)");
        return;
    }
    if std::env::var_os("ORT_DYLIB_PATH").is_none_or(|p| p.is_empty()) {
        eprintln!("tradeoffs: skipped, ORT_DYLIB_PATH is not set (source scripts/env.sh)");
        return;
    }
    let quick = std::env::var_os("C4G_TRADEOFFS_QUICK").is_some_and(|v| !v.is_empty() && v != "0");
    let out = std::env::var_os("C4G_TRADEOFFS_OUT")
        .map(PathBuf::from)
        .unwrap_or_else(|| common::workspace().join("target/tradeoffs.json"));
    let started = Instant::now();
    let load_start = load_average();
    let settings = sweep(quick);
    let mut wanted: Vec<&'static str> = settings.iter().map(|s| s.precision).collect();
    wanted.dedup();
    let scratch = tempfile::tempdir().unwrap();
    let (package_dirs, mut notes) = packages(scratch.path(), &wanted);
    let f32_engine = Engine::load(common::tiny_dir(), EngineOptions::default()).unwrap();
    let mut names = common::tiny_clip_names();
    if quick {
        names.truncate(1);
    }
    let clips: Vec<Clip> = names.iter().map(|n| load_clip(&f32_engine, n)).collect();
    let mut harness = Harness {
        clips,
        rasterizer: CpuRasterizer::new(),
        encodings: HashMap::new(),
        references: HashMap::new(),
    };
    let machine = machine();
    eprintln!(
        "tradeoffs: {} settings on {} clip(s); machine: {machine}",
        settings.len(),
        harness.clips.len(),
    );
    // Every package's engine, loaded before the first setting, so each row's memory holds the same.
    let mut engines: HashMap<&'static str, Engine> = HashMap::new();
    for (&p, dir) in &package_dirs {
        if p != "f32" {
            engines.insert(p, Engine::load(dir, EngineOptions::default()).unwrap());
        }
    }
    let runnable: Vec<&Setting> = settings
        .iter()
        .filter(|s| s.precision == "f32" || engines.contains_key(s.precision))
        .collect();
    let engine_for = |s: &Setting| -> &Engine {
        if s.precision == "f32" {
            &f32_engine
        } else {
            &engines[s.precision]
        }
    };
    let mut prepared: Vec<Prepared> = Vec::new();
    for s in &runnable {
        prepared.push(harness.first(s, engine_for(s), &f32_engine));
        let row = &prepared.last().unwrap().row;
        eprintln!(
            "  {:<56} GT {:>5.2} dB  vs exact {:>9} dB  {:>6.1} decodes  {:>5.0} B/frame f16  peak {:>4.0} MiB  {:>6.1} ms/frame",
            s.name,
            row["gt"]["psnr"].as_f64().unwrap(),
            fmt_opt(&row["vs_exact"]["psnr"]),
            row["exact_decodes_per_clip"].as_f64().unwrap(),
            row["bytes_per_frame_f16"].as_f64().unwrap(),
            row["peak_rss_mib"].as_f64().unwrap_or(0.0),
            prepared.last().unwrap().rounds[0] * 1e3 / (OUTPUT_FRAMES * harness.clips.len()) as f64,
        );
    }
    // Later rounds time every setting again, each in its own shuffled order, so that a burst of
    // load from elsewhere on the machine costs a setting one round, not all of its runs.
    let budget = std::env::var("C4G_TRADEOFFS_BUDGET_S")
        .ok()
        .and_then(|v| v.parse::<f64>().ok())
        .unwrap_or(BUDGET_S);
    let mut rounds = 1;
    let mut last_round_s = 0.0;
    while !quick
        && rounds < MAX_ROUNDS
        && (rounds < MIN_ROUNDS || started.elapsed().as_secs_f64() + last_round_s < budget)
    {
        let round = rounds;
        rounds += 1;
        let round_started = Instant::now();
        let order = shuffled(runnable.len(), round as u64);
        for i in order {
            let s = runnable[i];
            harness.again(s, engine_for(s), &mut prepared[i]);
        }
        last_round_s = round_started.elapsed().as_secs_f64();
        eprintln!(
            "tradeoffs: round {} in {last_round_s:.0} s ({:.0} s so far)",
            round + 1,
            started.elapsed().as_secs_f64()
        );
    }
    let clip_count = harness.clips.len();
    let rows: Vec<Value> = prepared.into_iter().map(|p| p.finish(clip_count)).collect();
    for row in &rows {
        eprintln!(
            "{:<56} {:>7.2} ms/frame (decode {:>5.1}%) {:>8.0} sets/s  GT {:>5.2} dB  vs exact {:>9} dB",
            row["name"].as_str().unwrap(),
            row["ms_per_frame"].as_f64().unwrap(),
            100.0 * row["decode_share"].as_f64().unwrap(),
            row["sets_per_s"].as_f64().unwrap(),
            row["gt"]["psnr"].as_f64().unwrap(),
            fmt_opt(&row["vs_exact"]["psnr"]),
        );
    }
    if rows.iter().any(|r| r["peak_reset"] == false) {
        notes.push("peak memory could not be reset (/proc/self/clear_refs): peaks are the process's since start".into());
    }
    let results = json!({
        "harness": "cargo bench -p c4g-engine --bench tradeoffs",
        "quick": quick,
        "package": "c4g-tiny",
        "gaussians": f32_engine.manifest().gaussian_count,
        "clips": names,
        "output_frames": OUTPUT_FRAMES,
        "rounds": rounds,
        "timing": "per clip the best of the rounds (each round times every setting once, in its own shuffled order; at least 3, more while the time budget allows), summed over clips; wall time on this machine",
        "analysis": {
            "times": ANALYSIS_TIMES,
            "views": "every context frame's camera, and a ring of 4 novel views: an orbit about the point 2 units ahead of the first context camera at -15, -7.5, +7.5 and +15 degrees",
            "resolution": "the setting's render resolution",
        },
        "context_frames": "T of each clip's 7 frames (0-0.6 s at 10 fps) spread evenly, both ends included: T=2: 0 6; 3: 0 3 6; 4: 0 2 4 6 (the clips' own); 6: 0 1 2 4 5 6",
        "ground_truth": "the 3 targets (0.1, 0.3, 0.5 s) from the clip's camera (interpolated) and from the novel camera, at 64 px; renders above 64 px box-downsampled",
        "machine": machine,
        "load_average": {"start": load_start, "end": load_average()},
        "elapsed_s": started.elapsed().as_secs_f64(),
        "notes": notes,
        "settings": rows,
    });
    if let Some(parent) = out.parent() {
        std::fs::create_dir_all(parent).unwrap();
    }
    std::fs::write(&out, serde_json::to_string_pretty(&results).unwrap()).unwrap();
    let out = out.canonicalize().unwrap_or(out);
    for note in &notes {
        eprintln!("note: {note}");
    }
    eprintln!(
        "tradeoffs: wrote {} in {:.0} s",
        out.display(),
        started.elapsed().as_secs_f64()
    );
}
