//! Shared helpers of the engine's integration tests: where the fixture package, the shared data
//! and ONNX Runtime are, and deterministic synthetic frames.
#![allow(dead_code, clippy::unwrap_used, clippy::expect_used)]

use std::path::PathBuf;
use std::sync::OnceLock;

use c4g_engine::{ContextFrame, Engine, EngineOptions, TimePolicy};

/// Frame size of the fixture package.
pub const SIZE: usize = 224;

pub fn workspace() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..")
}

pub fn fixture_dir() -> PathBuf {
    workspace().join("models/fixtures/c4g-small")
}

pub fn shared_dir() -> PathBuf {
    std::env::var_os("C4G_SHARED")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join("../shared"))
}

/// Why the tests that need ONNX Runtime and the fixture cannot run here, if they cannot.
///
/// Outside CI a missing piece skips the test with a message; in CI (`CI` set) it fails, so a
/// misconfigured CI cannot pass by running nothing.
pub fn skip_reason() -> Option<String> {
    let reason = if std::env::var_os("ORT_DYLIB_PATH").is_none_or(|p| p.is_empty()) {
        Some(
            "ORT_DYLIB_PATH is not set (point it at libonnxruntime.so from the onnxruntime wheel)"
                .to_owned(),
        )
    } else if !fixture_dir().join("model.json").is_file() {
        Some(format!(
            "fixture package {} not found",
            fixture_dir().display()
        ))
    } else {
        None
    };
    if let Some(reason) = &reason {
        assert!(
            std::env::var_os("CI").is_none(),
            "in CI every engine test must run: {reason}"
        );
        eprintln!("skipped: {reason}");
    }
    reason
}

/// The fixture package with default options (its own time policy: frame-step, as it declares
/// none), loaded once per test binary.
pub fn engine() -> &'static Engine {
    static ENGINE: OnceLock<Engine> = OnceLock::new();
    ENGINE.get_or_init(|| Engine::load(fixture_dir(), EngineOptions::default()).unwrap())
}

/// The fixture package with the stable time policy, loaded once per test binary: what the
/// mirror's stable reference outputs were made with.
pub fn stable_engine() -> &'static Engine {
    static ENGINE: OnceLock<Engine> = OnceLock::new();
    ENGINE.get_or_init(|| {
        let options = EngineOptions {
            time_policy: Some(TimePolicy::Stable),
            ..EngineOptions::default()
        };
        Engine::load(fixture_dir(), options).unwrap()
    })
}

/// A deterministic, non-constant preprocessed frame (values in [-1, 1]), different per `seed`.
pub fn synthetic_pixels(seed: u32) -> Vec<f32> {
    let mut out = Vec::with_capacity(3 * SIZE * SIZE);
    for c in 0..3u32 {
        for y in 0..SIZE as u32 {
            for x in 0..SIZE as u32 {
                let phase = (x * (c + 1) + y * 3 + seed * 17) as f32 * 0.05;
                out.push((phase.sin() * 0.8 + (seed as f32 * 0.1).cos() * 0.1).clamp(-1.0, 1.0));
            }
        }
    }
    out
}

/// Context frames at `times`, frame `i` with `synthetic_pixels(i)`.
pub fn synthetic_frames(times: &[f64]) -> Vec<ContextFrame> {
    times
        .iter()
        .enumerate()
        .map(|(i, &t)| ContextFrame::new(t, synthetic_pixels(i as u32)))
        .collect()
}

/// Largest absolute difference between two equally long slices.
pub fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

/// The default model's package (`models/c4g-tiny`).
pub fn tiny_dir() -> PathBuf {
    workspace().join("models/c4g-tiny")
}

/// One of c4g-tiny's committed test clips (`test-clips/<name>`, from its `clip.json`): the times
/// of all its frames and its context frames, preprocessed by `engine`.
pub struct TinyClip {
    /// Every frame's time, seconds (targets included).
    pub times: Vec<f64>,
    /// The context frames.
    pub context: Vec<ContextFrame>,
}

pub fn tiny_clip(engine: &Engine, name: &str) -> TinyClip {
    let dir = tiny_dir().join("test-clips").join(name);
    let meta: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("clip.json")).unwrap()).unwrap();
    let times: Vec<f64> = serde_json::from_value(meta["times"].clone()).unwrap();
    let names: Vec<String> = serde_json::from_value(meta["frames"].clone()).unwrap();
    let indices: Vec<usize> = serde_json::from_value(meta["context"].clone()).unwrap();
    let context = indices
        .iter()
        .map(|&i| {
            let image = image::open(dir.join(&names[i])).unwrap().to_rgb8();
            ContextFrame::new(times[i], engine.preprocess(&image).unwrap())
        })
        .collect();
    TinyClip { times, context }
}

/// The names of c4g-tiny's test clips, sorted.
pub fn tiny_clip_names() -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(tiny_dir().join("test-clips"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

/// The machine line of the benches' reports: the CPU's model and threads, and that the work
/// runs on the CPU (ONNX Runtime's CPU execution provider, the CPU rasterizer).
pub fn machine() -> String {
    let cpuinfo = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let cpu = cpuinfo
        .lines()
        .find(|l| l.starts_with("model name"))
        .and_then(|l| l.split(':').nth(1))
        .map_or("unknown CPU".to_owned(), |s| s.trim().to_owned());
    let threads = std::thread::available_parallelism().map_or(0, usize::from);
    format!(
        "{cpu}, {threads} threads, no GPU (ONNX Runtime's CPU execution provider, the CPU rasterizer)"
    )
}

/// The load average over 1, 5 and 15 minutes, as `/proc/loadavg` gives it: what a report says
/// of how shared the machine was.
pub fn load_average() -> String {
    std::fs::read_to_string("/proc/loadavg")
        .map(|s| s.split_whitespace().take(3).collect::<Vec<_>>().join(" "))
        .unwrap_or_default()
}
