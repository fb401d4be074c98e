//! Cost of refinement: one transformer step, the control input, the decoder, and whole runs by
//! step count, on the fixture package by default.
//!
//!     cargo bench -p c4g-refiner --bench refine
//!     C4G_BENCH_PACKAGE=/tmp/wan-vace-1.3b-random cargo bench -p c4g-refiner --bench refine
//!
//! Packages have a fixed video size, so the frame-count axis is one package per size: the second
//! form adds a package (for example `python -m c4g.wan.export --random-init --config 1.3b
//! --frames 17 ...`) next to the fixture, and its group is labelled with its frames x height x
//! width. Seconds per step = a `velocity` run (guidance 1) or two (guidance ≠ 1). The machine line
//! printed first goes with the numbers into docs/benchmarks.md.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use std::ops::ControlFlow;
use std::path::PathBuf;
use std::time::Duration;

use c4g_refiner::lora::LoraModule;
use c4g_refiner::lora::merge::merge_into;
use c4g_refiner::{Mask, Pipeline, PipelineOptions, RefineRequest, Sampler, gaussian_noise};
use criterion::{BenchmarkId, Criterion, criterion_group, criterion_main};

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
    let threads = std::thread::available_parallelism().map_or(0, usize::from);
    format!("{cpu}, {threads} threads")
}

fn packages() -> Vec<PathBuf> {
    let mut dirs =
        vec![PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../models/fixtures/wan-vace-tiny")];
    if let Some(extra) = std::env::var_os("C4G_BENCH_PACKAGE") {
        dirs.push(PathBuf::from(extra));
    }
    dirs
}

/// A request of the package's size: half context frames, half rendered, smooth content.
fn request(pipeline: &Pipeline, steps: usize, guidance: f32) -> RefineRequest {
    let m = pipeline.manifest();
    let video = (0..m.frames)
        .map(|t| {
            (0..m.frame_len())
                .map(|i| (i as f32 * 0.013 + t as f32 * 0.1).sin() * 0.4 + 0.5)
                .collect()
        })
        .collect();
    let mask = Mask::Frames((0..m.frames).map(|t| t >= m.frames / 2).collect());
    let text = gaussian_noise(1, m.text_len());
    let mut r = RefineRequest::new(video, mask, text);
    r.negative_embeddings = Some(vec![0.0; m.text_len()]);
    r.steps = steps;
    r.guidance = guidance;
    r.sampler = Sampler::UniPc;
    r
}

fn bench(c: &mut Criterion) {
    if std::env::var_os("ORT_DYLIB_PATH").is_none_or(|p| p.is_empty()) {
        eprintln!("skipped: ORT_DYLIB_PATH is not set");
        return;
    }
    eprintln!("machine: {}", machine());
    for dir in packages() {
        let pipeline = Pipeline::load(&dir, &PipelineOptions::default()).unwrap();
        let m = pipeline.manifest();
        let label = format!("{} {}x{}x{}", m.name, m.frames, m.height, m.width);
        let mut group = c.benchmark_group(format!("refine/{label}"));
        group
            .sample_size(10)
            .measurement_time(Duration::from_secs(10));

        let r = request(&pipeline, 1, 1.0);
        let control = pipeline.control(&r.video, &r.mask).unwrap();
        let latents = gaussian_noise(2, m.latent_len());
        let scales = vec![1.0; m.vace_layers.len()];
        group.bench_function("control (VAE encode x2)", |b| {
            b.iter(|| pipeline.control(&r.video, &r.mask).unwrap())
        });
        group.bench_function("transformer step (one velocity)", |b| {
            b.iter(|| {
                pipeline
                    .velocity(&latents, 500.0, &r.text_embeddings, &control, &scales)
                    .unwrap()
            })
        });
        group.bench_function("decode", |b| b.iter(|| pipeline.decode(&latents).unwrap()));
        for guidance in [1.0, 5.0] {
            for steps in [1, 2, 4, 8] {
                let r = request(&pipeline, steps, guidance);
                group.bench_with_input(
                    BenchmarkId::new(format!("refine guidance {guidance}"), steps),
                    &r,
                    |b, r| {
                        b.iter(|| {
                            pipeline
                                .refine(r, &mut |_, _| ControlFlow::Continue(()))
                                .unwrap()
                        })
                    },
                );
            }
        }
        group.finish();
    }
}

/// Merging one rank-128 LoRA module into a weight of the 1.3B model (attention 1536 x 1536, FFN
/// 8960 x 1536); the model has 30 + 15 blocks of 8 attention and 2 FFN linears.
fn merge(c: &mut Criterion) {
    let mut group = c.benchmark_group("lora merge (rank 128)");
    group.sample_size(10);
    for (rows, cols) in [(1536, 1536), (8960, 1536)] {
        let rank = 128;
        let module = LoraModule {
            source: "m".to_owned(),
            module: "m".to_owned(),
            down: gaussian_noise(1, rank * cols),
            down_shape: vec![rank, cols],
            up: gaussian_noise(2, rows * rank),
            up_shape: vec![rows, rank],
            scale: 1.0,
        };
        let weight = gaussian_noise(3, rows * cols);
        group.bench_function(format!("{rows}x{cols}"), |b| {
            b.iter(|| {
                let mut w = weight.clone();
                merge_into(&mut w, &module, 1.0).unwrap();
                w
            })
        });
    }
    group.finish();
}

criterion_group!(benches, merge, bench);
criterion_main!(benches);
