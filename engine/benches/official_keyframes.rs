//! Keyframed decoding at the official decoder's size: a 64-frame output from 16 context frames,
//! decoded exactly and with the quality presets' keyframes, timed and rendered.
//!
//!     C4G_OFFICIAL_KEYFRAMES_PACKAGE=/tmp/c4g-official-decoder \
//!         nice cargo bench -p c4g-engine --bench official_keyframes    # ~20 min on 2 cores
//!
//!     $PYTHON -m c4g.bench.tradeoffs_report --section official-keyframes=target/official-keyframes.md --out docs
//!
//! The package is one at the official decoder's size with random weights and a one-block encoder
//! (`python -m c4g.package.export --random-init --config CONFIG`, CONFIG the official sizes with
//! `dino_depth` and `aggregator_depth` 1: the official decoder, in the precomputed form the
//! export tool writes from width 512 up, fed features of its width by an encoder that is cheap to
//! export and run). Without the variable the bench prints how to make one and does nothing.
//!
//! **What it runs.** 16 synthetic context frames at source frames 0, 2, …, 30 of a 30 fps clip
//! (stride 2, as the reference samples them; the encoding carries the 1/30 s source step that the
//! package's `frame-step` time policy reads), then 64 output times evenly over the span, decoded:
//! exactly (64 exact decodes, batched as the engine batches); with the presets' keyframes as
//! `service/src/sets/quality.rs` makes them for a clip (`balanced`: a keyframe every context spacing;
//! `fast`: every 1.5 spacings; `fast`'s pruning changes what is rendered, not what is decoded, and
//! is left out); and with 8 and 4 uniform keyframes. Each of those is timed once as
//! `Engine::decode_keyframed` runs it (its exact decodes and the interpolation), against the exact
//! decodes' time in the same run. Adaptive tolerances are *counted*, not timed: every set an
//! adaptive plan decodes is a context time (which `balanced` decoded) or a requested time (which
//! the exact run decoded), so the engine's planner (`plan_keyframes`) runs on those sets, and the
//! setting's time is its exact decodes at the exact run's time per decode plus its own planning
//! and interpolation. An exact decode here takes seconds and the machine is shared: the ratios
//! are firmer than the seconds, and the decode counts (the engine's `KeyframeStats`) firmer still.
//!
//! **What it compares.** Every set rendered at 224 px (the model's input size, C4G's intrinsics)
//! from the first context camera and from a novel camera (moved (0.15, −0.05, 0.1) and turned 6°,
//! as the tradeoffs sweep's), with the footprint the package declares (3DGS tiles for an
//! official-layout package), on the CPU rasterizer. PSNR against the exact renders, pooled over
//! all 128 frames and the worst frame; and per Gaussian the position error against the exact set
//! (largest and mean over every Gaussian and time), beside how far the exact Gaussians move over
//! the span, so that the error can be read against the motion it interpolates.
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

#[path = "../tests/common/mod.rs"]
mod common;

use common::{load_average, machine};

use std::collections::HashMap;
use std::fmt::Write as _;
use std::time::Instant;

use c4g_engine::keyframes::plan_keyframes;
use c4g_engine::{ContextFrame, Encoding, Engine, EngineOptions, KeyframeStats, Keyframes};
use c4g_renderer::{CpuRasterizer, Rasterizer, RenderOptions};
use c4g_scene::{Camera, GaussianSet, NormalizedIntrinsics};
use glam::{Affine3A, Quat, Vec3};

const CONTEXT_FRAMES: usize = 16;
/// Source frames between context frames, and the source's frame rate.
const STRIDE: f64 = 2.0;
const FPS: f64 = 30.0;
const TARGETS: usize = 64;
const SIZE: u32 = 224;

/// One way of producing the 64 sets.
struct Setting {
    name: String,
    keyframes: Keyframes,
    /// Counted, not timed: planned from sets already decoded, its time the decodes it needs at
    /// the exact run's time per decode plus its own interpolation.
    counted: bool,
}

/// What one setting produced and cost.
struct Outcome {
    name: String,
    seconds: f64,
    counted: bool,
    stats: KeyframeStats,
    pooled_db: f64,
    worst_db: f64,
    worst_context_db: f64,
    worst_novel_db: f64,
    position_max: f64,
    position_mean: f64,
}

fn main() {
    if std::env::args()
        .skip(1)
        .any(|a| !a.starts_with('-') && !"official_keyframes".contains(&a))
    {
        return;
    }
    let Some(dir) = std::env::var_os("C4G_OFFICIAL_KEYFRAMES_PACKAGE") else {
        println!(
            "official_keyframes: set C4G_OFFICIAL_KEYFRAMES_PACKAGE to a package at the official decoder's size \
             (python -m c4g.package.export --random-init --config CONFIG --out DIR, CONFIG the official sizes with \
             dino_depth and aggregator_depth 1)"
        );
        return;
    };
    if common::skip_reason().is_some() {
        return;
    }
    let start = Instant::now();
    let load_start = load_average();
    let engine = Engine::load(&dir, EngineOptions::default()).unwrap();
    let m = engine.manifest();
    assert_eq!(
        m.input.width as usize,
        common::SIZE,
        "synthetic frames are {0}x{0}",
        common::SIZE
    );
    let step = 1.0 / FPS;
    let spacing = STRIDE * step;
    let frames: Vec<ContextFrame> = (0..CONTEXT_FRAMES)
        .map(|i| ContextFrame::new(i as f64 * spacing, common::synthetic_pixels(i as u32)))
        .collect();
    let t = Instant::now();
    let encoding = engine
        .encode(&frames)
        .unwrap()
        .with_frame_step(Some(step))
        .unwrap();
    let encode_s = t.elapsed().as_secs_f64();
    let (first, last) = encoding.time_span();
    let times: Vec<f64> = (0..TARGETS)
        .map(|i| first + (last - first) * i as f64 / (TARGETS - 1) as f64)
        .collect();
    let footprint = engine.manifest().footprint();
    let options = RenderOptions {
        footprint,
        ..RenderOptions::default()
    };
    let cameras = cameras();
    eprintln!(
        "encoded {CONTEXT_FRAMES} frames in {encode_s:.1} s; decoding {TARGETS} times exactly"
    );

    let t = Instant::now();
    let (exact, exact_stats) = engine
        .decode_keyframed(&encoding, &times, &Keyframes::Exact)
        .unwrap();
    let exact_s = t.elapsed().as_secs_f64();
    eprintln!(
        "exact: {exact_s:.1} s, {} decodes",
        exact_stats.exact_decodes
    );
    let exact_renders = renders(&exact, &cameras, &options);
    let motion = motion(&exact);

    // Every set decoded exactly so far, by time: the counted settings plan from these.
    let mut decoded: HashMap<u64, GaussianSet> = times
        .iter()
        .zip(&exact)
        .map(|(t, s)| (t.to_bits(), s.clone()))
        .collect();
    let mut outcomes = vec![Outcome {
        name: "exact".to_owned(),
        seconds: exact_s,
        counted: false,
        stats: exact_stats,
        pooled_db: f64::INFINITY,
        worst_db: f64::INFINITY,
        worst_context_db: f64::INFINITY,
        worst_novel_db: f64::INFINITY,
        position_max: 0.0,
        position_mean: 0.0,
    }];
    let per_decode = exact_s / TARGETS as f64;
    let batch = engine.decode_batch_size(CONTEXT_FRAMES).max(1);
    for setting in settings(spacing) {
        let (sets, seconds, stats) = if setting.counted {
            counted_decode(
                &encoding,
                &times,
                &setting.keyframes,
                &decoded,
                per_decode,
                batch,
            )
        } else {
            timed_decode(&engine, &encoding, &times, &setting.keyframes, &mut decoded)
        };
        eprintln!(
            "{}: {seconds:.1} s{}, {} decodes ({:.3} of exact's time)",
            setting.name,
            if setting.counted { " (counted)" } else { "" },
            stats.exact_decodes,
            seconds / exact_s
        );
        let (position_max, position_mean) = position_error(&exact, &sets);
        let ours = renders(&sets, &cameras, &options);
        let (pooled_db, worst_db) = psnr(&exact_renders, &ours);
        let per_camera = |c: usize| {
            let pick = |r: &[Vec<f32>]| {
                r.iter()
                    .skip(c)
                    .step_by(cameras.len())
                    .cloned()
                    .collect::<Vec<_>>()
            };
            psnr(&pick(&exact_renders), &pick(&ours)).1
        };
        outcomes.push(Outcome {
            name: setting.name.clone(),
            seconds,
            counted: setting.counted,
            stats,
            pooled_db,
            worst_db,
            worst_context_db: per_camera(0),
            worst_novel_db: per_camera(1),
            position_max,
            position_mean,
        });
    }

    let doc = document(&Report {
        engine: &engine,
        encode_s,
        spacing,
        footprint: footprint_name(footprint),
        motion,
        outcomes: &outcomes,
        wall_s: start.elapsed().as_secs_f64(),
        load_start,
        batch: engine.decode_batch_size(CONTEXT_FRAMES),
    });
    let out = std::env::var("C4G_OFFICIAL_KEYFRAMES_OUT").unwrap_or_else(|_| {
        common::workspace()
            .join("target/official-keyframes.md")
            .display()
            .to_string()
    });
    std::fs::write(&out, &doc).unwrap();
    println!("{doc}\nwritten to {out}");
}

/// The settings measured against exact, timed: the presets' keyframes for this clip and uniform
/// counts of 8 (1/8 of the decodes) and 4; counted: adaptive tolerances
/// (`C4G_OFFICIAL_KEYFRAMES_TOLERANCES`, comma-separated scene units) and 16 keyframes. Every set
/// a counted setting decodes is one a timed one decoded before it (an adaptive plan's keyframes
/// are the context times, which `balanced` decodes, and requested times, which exact does).
fn settings(spacing: f64) -> Vec<Setting> {
    let timed = |name: String, keyframes| Setting {
        name,
        keyframes,
        counted: false,
    };
    let every = |name: &str, spacings: f64| {
        timed(
            format!("{name}: every {spacings} context spacings"),
            Keyframes::Every {
                seconds: spacings * spacing,
            },
        )
    };
    let mut settings = vec![
        every("balanced", 1.0),
        every("fast", 1.5),
        timed("count 8".to_owned(), Keyframes::Count { n: 8 }),
        timed("count 4".to_owned(), Keyframes::Count { n: 4 }),
    ];
    let tolerances = std::env::var("C4G_OFFICIAL_KEYFRAMES_TOLERANCES")
        .unwrap_or_else(|_| "0.05,0.01,0.002".to_owned());
    for tolerance in tolerances.split(',').filter(|s| !s.trim().is_empty()) {
        let tolerance: f64 = tolerance.trim().parse().unwrap();
        settings.push(Setting {
            name: format!("adaptive {tolerance}"),
            keyframes: Keyframes::adaptive(tolerance, Keyframes::DEFAULT_MAX_KEYFRAMES),
            counted: true,
        });
    }
    settings
}

/// One keyframed decode as `Engine::decode_keyframed` makes it (its keyframes decoded, the
/// rest interpolated), timed; its keyframes go into `decoded`.
fn timed_decode(
    engine: &Engine,
    encoding: &Encoding,
    times: &[f64],
    keyframes: &Keyframes,
    decoded: &mut HashMap<u64, GaussianSet>,
) -> (Vec<GaussianSet>, f64, KeyframeStats) {
    let t = Instant::now();
    let (track, mut stats) = engine.keyframe_track(encoding, times, keyframes).unwrap();
    let sets: Vec<GaussianSet> = times.iter().map(|&t| track.at(t).unwrap()).collect();
    let seconds = t.elapsed().as_secs_f64();
    stats.interpolated = times
        .iter()
        .filter(|&&t| track.keyframe(t).is_none())
        .count();
    for (t, set) in track.times().iter().zip(track.sets()) {
        decoded.entry(t.to_bits()).or_insert_with(|| set.clone());
    }
    (sets, seconds, stats)
}

/// One keyframed decode planned by the engine's own planner (`plan_keyframes`, which
/// `decode_keyframed` runs) with every set it asks for taken from `decoded`; its time is
/// its decodes at `per_decode` each plus what the planning and interpolation took.
fn counted_decode(
    encoding: &Encoding,
    times: &[f64],
    keyframes: &Keyframes,
    decoded: &HashMap<u64, GaussianSet>,
    per_decode: f64,
    batch: usize,
) -> (Vec<GaussianSet>, f64, KeyframeStats) {
    let t = Instant::now();
    let mut runs = 0;
    let (track, mut stats) = plan_keyframes(times, keyframes, encoding.times(), |at| {
        runs += at.len().div_ceil(batch);
        Ok(at
            .iter()
            .map(|t| {
                decoded
                    .get(&t.to_bits())
                    .unwrap_or_else(|| panic!("t = {t} was decoded by no timed setting"))
                    .clone()
            })
            .collect())
    })
    .unwrap();
    let sets: Vec<GaussianSet> = times.iter().map(|&t| track.at(t).unwrap()).collect();
    let own = t.elapsed().as_secs_f64();
    stats.decoder_runs = runs;
    stats.interpolated = times
        .iter()
        .filter(|&&t| track.keyframe(t).is_none())
        .count();
    (sets, stats.exact_decodes as f64 * per_decode + own, stats)
}

/// The first context camera and the novel one.
fn cameras() -> Vec<Camera> {
    let camera = |world_to_camera| {
        Camera::from_normalized(
            NormalizedIntrinsics::C4G_DEFAULT,
            SIZE,
            SIZE,
            world_to_camera,
        )
        .unwrap()
    };
    let novel_to_world = Affine3A::from_rotation_translation(
        Quat::from_rotation_y(6f32.to_radians()),
        Vec3::new(0.15, -0.05, 0.1),
    );
    vec![camera(Affine3A::IDENTITY), camera(novel_to_world.inverse())]
}

/// Renders of `sets` from `cameras`, RGB per frame, frame by frame camera by camera.
fn renders(sets: &[GaussianSet], cameras: &[Camera], options: &RenderOptions) -> Vec<Vec<f32>> {
    let rasterizer = CpuRasterizer::new();
    sets.iter()
        .flat_map(|s| {
            cameras
                .iter()
                .map(|c| rasterizer.render(s, c, options).unwrap().rgb)
        })
        .collect()
}

/// PSNR pooled over all frames, and the worst frame's (peak 1; `inf` when identical).
fn psnr(exact: &[Vec<f32>], other: &[Vec<f32>]) -> (f64, f64) {
    let db = |se: f64, count: usize| -10.0 * (se / count as f64).log10();
    let (mut total, mut count, mut worst) = (0.0, 0, f64::INFINITY);
    for (a, b) in exact.iter().zip(other) {
        let se: f64 = a
            .iter()
            .zip(b)
            .map(|(x, y)| f64::from(x.clamp(0.0, 1.0) - y.clamp(0.0, 1.0)).powi(2))
            .sum();
        total += se;
        count += a.len();
        worst = worst.min(db(se, a.len()));
    }
    (db(total, count), worst)
}

/// Largest and mean distance between a Gaussian's position in `a` and in `b`, over every
/// Gaussian of every set.
fn position_error(a: &[GaussianSet], b: &[GaussianSet]) -> (f64, f64) {
    let (mut max, mut sum, mut count) = (0.0f64, 0.0, 0usize);
    for (sa, sb) in a.iter().zip(b) {
        for (pa, pb) in sa.positions().iter().zip(sb.positions()) {
            let d = distance(pa, pb);
            max = max.max(d);
            sum += d;
            count += 1;
        }
    }
    (max, sum / count as f64)
}

fn distance(a: &[f32; 3], b: &[f32; 3]) -> f64 {
    (0..3)
        .map(|k| (f64::from(a[k]) - f64::from(b[k])).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// How the exact Gaussians move and where they are: each one's path length over the 64 sets
/// (the sum of its steps; mean and largest) and the median distance of the Gaussians from the
/// first context camera.
struct Motion {
    path_mean: f64,
    path_max: f64,
    step_mean: f64,
    median_depth: f64,
}

fn motion(sets: &[GaussianSet]) -> Motion {
    let n = sets[0].len();
    let mut paths = vec![0.0f64; n];
    for w in sets.windows(2) {
        for (i, (a, b)) in w[0].positions().iter().zip(w[1].positions()).enumerate() {
            paths[i] += distance(a, b);
        }
    }
    let mut depths: Vec<f64> = sets[0]
        .positions()
        .iter()
        .map(|p| distance(p, &[0.0; 3]))
        .collect();
    depths.sort_by(f64::total_cmp);
    let path_mean = paths.iter().sum::<f64>() / n as f64;
    Motion {
        path_mean,
        path_max: paths.iter().copied().fold(0.0, f64::max),
        step_mean: path_mean / (sets.len() - 1) as f64,
        median_depth: depths[n / 2],
    }
}

fn footprint_name(footprint: c4g_scene::Footprint) -> &'static str {
    match footprint {
        c4g_scene::Footprint::Ellipse => "ellipse (cut at 3 sigma)",
        c4g_scene::Footprint::Tiles3dgs => "3dgs (the original rasterizer's tiles)",
    }
}

struct Report<'a> {
    engine: &'a Engine,
    encode_s: f64,
    spacing: f64,
    footprint: &'static str,
    motion: Motion,
    outcomes: &'a [Outcome],
    wall_s: f64,
    load_start: String,
    batch: usize,
}

fn db(v: f64) -> String {
    if v.is_infinite() {
        "identical".to_owned()
    } else {
        format!("{v:.2}")
    }
}

fn document(r: &Report) -> String {
    let m = r.engine.manifest();
    let exact = &r.outcomes[0];
    let per_decode = exact.seconds / exact.stats.exact_decodes as f64;
    let mut doc = String::new();
    writeln!(
        doc,
        "## Keyframes at the official decoder's size: 64 frames from 16 context frames\n"
    )
    .unwrap();
    writeln!(
        doc,
        "Generated by `C4G_OFFICIAL_KEYFRAMES_PACKAGE=DIR cargo bench -p c4g-engine --bench official_keyframes` \
         (`engine/benches/official_keyframes.rs`), not by the sweep above, and put here by `$PYTHON -m \
         c4g.bench.tradeoffs_report --section official-keyframes=target/official-keyframes.md --out docs`, which keeps it \
         when the page is remade. **Machine:** {}; load average {} at the start, {} at the end; wall time {:.0} min.\n",
        machine(),
        r.load_start,
        load_average(),
        r.wall_s / 60.0
    )
    .unwrap();
    writeln!(
        doc,
        "**Package:** `{}` ({} Gaussians, decoder width {}, {} decoder form, {} time policy, footprint {}), random \
         weights, a one-block encoder: `python -m c4g.package.export --random-init --config CONFIG --out DIR`, CONFIG the \
         official sizes with `dino_depth` and `aggregator_depth` 1 (the decoder is the official one; the encoder \
         only has to give it features of its width). **Clip:** {CONTEXT_FRAMES} synthetic context frames, source \
         frames 0, 2, …, 30 of a {FPS} fps clip (context spacing {:.4} s, source step 1/{FPS} s), encoded in {:.1} s; \
         {TARGETS} output times evenly over the span, both ends included. Exact decodes run in batches of {} (the \
         engine's batch at T = {CONTEXT_FRAMES}): {:.2} s an exact decode in this run. Renders at {SIZE} px from the \
         first context camera and a novel one (moved (0.15, −0.05, 0.1), turned 6°), {} frames a setting.\n",
        m.name,
        m.gaussian_count,
        m.feature_width,
        match m.decoder_form {
            c4g_engine::package::DecoderForm::Plain => "plain",
            c4g_engine::package::DecoderForm::Precomputed => "precomputed",
        },
        r.engine.time_policy().name(),
        r.footprint,
        r.spacing,
        r.encode_s,
        r.batch,
        per_decode,
        2 * TARGETS
    )
    .unwrap();
    writeln!(
        doc,
        "| setting | exact decodes (decoder runs) | decode time | vs 64 exact decodes (time · decodes) | ≤ 1/8 | PSNR vs exact, pooled | worst frame (context camera · novel) | position error max / mean |"
    )
    .unwrap();
    writeln!(doc, "|---|---|---|---|---|---|---|---|").unwrap();
    for o in r.outcomes {
        let ratio = o.seconds / exact.seconds;
        let decodes = o.stats.exact_decodes as f64 / TARGETS as f64;
        writeln!(
            doc,
            "| {} | {} ({}) | {}{:.1} s | {ratio:.3} · {decodes:.3} | {} | {} | {} ({} · {}) | {:.4} / {:.5} |",
            o.name,
            o.stats.exact_decodes,
            o.stats.decoder_runs,
            if o.counted { "≈ " } else { "" },
            o.seconds,
            if ratio <= 0.125 { "yes" } else { "no" },
            db(o.pooled_db),
            db(o.worst_db),
            db(o.worst_context_db),
            db(o.worst_novel_db),
            o.position_max,
            o.position_mean,
        )
        .unwrap();
    }
    writeln!(doc).unwrap();
    writeln!(
        doc,
        "Times marked ≈ are counted, not timed: those settings were planned by the engine's own planner \
         (`plan_keyframes`, what `decode_keyframed` runs) from sets the timed ones had decoded, and their time is \
         their exact decodes at this run's time per decode plus their own planning and interpolation. The exact \
         Gaussians: median distance {:.3} from the first camera; each moves {:.4} on average between consecutive \
         output times, along a path of {:.3} on average (at most {:.3}) over the span.\n",
        r.motion.median_depth,
        r.motion.step_mean,
        r.motion.path_mean,
        r.motion.path_max,
    )
    .unwrap();
    doc
}
