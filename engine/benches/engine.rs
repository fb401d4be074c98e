//! Encode time and decode throughput of the engine, on the fixture package by default.
//!
//!     cargo bench -p c4g-engine --bench engine
//!     C4G_BENCH_PACKAGE=/tmp/c4g-official-random cargo bench -p c4g-engine --bench engine -- official
//!
//! The second form measures a package at the official dimensions with random weights (made by
//! `python -m c4g.package.export --random-init --config official`): size, not weights, sets the cost.
//! `-- keyframes` measures keyframed decoding on c4g-tiny (64 output times of its first test clip:
//! exact, 8 uniform keyframes, adaptive), and prints each mode's decodes and error against exact.
//! Results go in docs/benchmarks.md with the machine line this prints.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

// The integration tests' helpers: where the packages and c4g-tiny's test clips are.
#[path = "../tests/common/mod.rs"]
mod common;

use std::path::PathBuf;
use std::time::Duration;

use c4g_engine::keyframes::{Deviation, deviation};
use c4g_engine::{ContextFrame, Encoding, Engine, EngineOptions, Keyframes};
use criterion::{BenchmarkId, Criterion, Throughput, criterion_group, criterion_main};

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
    let threads = std::thread::available_parallelism().map_or(0, usize::from);
    format!("{cpu}, {threads} threads, {mem_gib:.0} GiB")
}

fn frames(engine: &Engine, count: usize) -> Vec<ContextFrame> {
    let input = &engine.manifest().input;
    let len = 3 * input.height as usize * input.width as usize;
    (0..count)
        .map(|i| {
            let pixels = (0..len)
                .map(|k| ((k * 31 + i * 7) % 97) as f32 / 48.5 - 1.0)
                .collect();
            ContextFrame::new(2.0 * i as f64, pixels)
        })
        .collect()
}

/// Targets spread evenly over the encoding's span.
fn targets(encoding: &Encoding, count: usize) -> Vec<f64> {
    let (lo, hi) = encoding.time_span();
    (0..count)
        .map(|i| lo + (hi - lo) * i as f64 / count.max(2).saturating_sub(1) as f64)
        .collect()
}

fn bench_package(
    c: &mut Criterion,
    label: &str,
    dir: PathBuf,
    encode_frames: &[usize],
    decode: &[(usize, usize)],
) {
    let engine = Engine::load(&dir, EngineOptions::default()).unwrap();
    eprintln!(
        "machine: {}; package: {} ({})",
        machine(),
        engine.manifest().name,
        dir.display()
    );
    let mut group = c.benchmark_group(format!("{label}/encode"));
    for &t in encode_frames {
        let input = frames(&engine, t);
        group.throughput(Throughput::Elements(t as u64));
        group.bench_with_input(BenchmarkId::new("frames", t), &input, |b, input| {
            b.iter(|| engine.encode(input).unwrap())
        });
    }
    group.finish();
    let mut group = c.benchmark_group(format!("{label}/decode"));
    for &(t, batch) in decode {
        let encoding = engine.encode(&frames(&engine, t)).unwrap();
        let times = targets(&encoding, batch);
        group.throughput(Throughput::Elements(batch as u64));
        group.bench_with_input(
            BenchmarkId::new(format!("T{t}/targets"), batch),
            &times,
            |b, times| b.iter(|| engine.decode(&encoding, times).unwrap()),
        );
    }
    group.finish();
}

fn fixture(c: &mut Criterion) {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../models/fixtures/c4g-small");
    let decode: Vec<(usize, usize)> = [4, 16]
        .iter()
        .flat_map(|&t| [1, 4, 16].map(|b| (t, b)))
        .collect();
    bench_package(c, "fixture", dir, &[4, 16], &decode);
}

fn official(c: &mut Criterion) {
    let Some(dir) = std::env::var_os("C4G_BENCH_PACKAGE") else {
        eprintln!(
            "official: set C4G_BENCH_PACKAGE to a package at the official size to measure it"
        );
        return;
    };
    bench_package(c, "official", dir.into(), &[4], &[(4, 1)]);
}

fn keyframes(c: &mut Criterion) {
    let engine = Engine::load(common::tiny_dir(), EngineOptions::default()).unwrap();
    eprintln!(
        "machine: {}; package: {}",
        machine(),
        engine.manifest().name
    );
    let encoding = engine
        .encode(&common::tiny_clip(&engine, "seed-2000000").context)
        .unwrap();
    let times = targets(&encoding, 64);
    let exact = engine.decode(&encoding, &times).unwrap();
    let modes = [
        ("exact", Keyframes::Exact),
        ("count8", Keyframes::Count { n: 8 }),
        ("count16", Keyframes::Count { n: 16 }),
        ("adaptive0.01", Keyframes::adaptive(0.01, 64)),
        ("adaptive0.005", Keyframes::adaptive(0.005, 64)),
        ("adaptive0.001", Keyframes::adaptive(0.001, 64)),
    ];
    let mut group = c.benchmark_group("tiny/keyframes64");
    group.throughput(Throughput::Elements(times.len() as u64));
    for (name, mode) in modes {
        let (sets, stats) = engine.decode_keyframed(&encoding, &times, &mode).unwrap();
        let worst = sets
            .iter()
            .zip(&exact)
            .map(|(a, b)| deviation(a, b).unwrap())
            .fold(Deviation::default(), |m, d| Deviation {
                position: m.position.max(d.position),
                appearance: m.appearance.max(d.appearance),
                rotation: m.rotation.max(d.rotation),
                log_scale: m.log_scale.max(d.log_scale),
            });
        eprintln!(
            "{name}: {} exact decodes in {} decoder runs, {} interpolated; largest error against \
             exact: position {:.2e}, colour/opacity {:.2e}, rotation {:.2e} rad",
            stats.exact_decodes,
            stats.decoder_runs,
            stats.interpolated,
            worst.position,
            worst.appearance,
            worst.rotation
        );
        group.bench_function(name, |b| {
            b.iter(|| engine.decode_keyframed(&encoding, &times, &mode).unwrap())
        });
    }
    group.finish();
}

criterion_group! {
    name = fixture_benches;
    config = Criterion::default().sample_size(10).warm_up_time(Duration::from_secs(1)).measurement_time(Duration::from_secs(10));
    targets = fixture
}
criterion_group! {
    name = official_benches;
    config = Criterion::default().sample_size(10).warm_up_time(Duration::from_millis(1)).measurement_time(Duration::from_secs(1));
    targets = official
}
criterion_group! {
    name = keyframe_benches;
    config = Criterion::default().sample_size(10).warm_up_time(Duration::from_millis(500)).measurement_time(Duration::from_secs(3));
    targets = keyframes
}
criterion_main!(fixture_benches, official_benches, keyframe_benches);
