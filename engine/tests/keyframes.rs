//! Keyframed decoding on real packages: exact where it must be (the exact mode, a tolerance of
//! 0), and, on the trained c4g-tiny, within the adaptive mode's tolerance at times it never
//! decoded, for fewer decodes than exact decoding.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::sync::OnceLock;

use c4g_engine::keyframes::{Deviation, deviation};
use c4g_engine::{Encoding, Engine, EngineOptions, Keyframes};
use c4g_scene::GaussianSet;

fn tiny() -> &'static Engine {
    static ENGINE: OnceLock<Engine> = OnceLock::new();
    ENGINE.get_or_init(|| Engine::load(common::tiny_dir(), EngineOptions::default()).unwrap())
}

/// The first committed test clip of c4g-tiny, its context frames encoded.
fn tiny_clip() -> Encoding {
    let clip = common::tiny_clip(tiny(), "seed-2000000");
    tiny().encode(&clip.context).unwrap()
}

/// `n` times spread evenly over the encoding's span, both ends included.
fn even(encoding: &Encoding, n: usize) -> Vec<f64> {
    let (lo, hi) = encoding.time_span();
    (0..n)
        .map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64)
        .collect()
}

/// Largest deviation of each kind over paired sets.
fn worst(a: &[GaussianSet], b: &[GaussianSet]) -> Deviation {
    a.iter()
        .zip(b)
        .map(|(x, y)| deviation(x, y).unwrap())
        .fold(Deviation::default(), |m, d| Deviation {
            position: m.position.max(d.position),
            appearance: m.appearance.max(d.appearance),
            rotation: m.rotation.max(d.rotation),
            log_scale: m.log_scale.max(d.log_scale),
        })
}

fn bits(sets: &[GaussianSet]) -> Vec<Vec<u32>> {
    sets.iter()
        .map(|s| s.to_canonical().iter().map(|v| v.to_bits()).collect())
        .collect()
}

#[test]
fn the_exact_mode_and_a_tolerance_of_zero_are_bitwise_the_plain_decode() {
    if common::skip_reason().is_some() {
        return;
    }
    let engine = common::engine();
    let encoding = engine
        .encode(&common::synthetic_frames(&[0.0, 1.0, 2.0, 3.0]))
        .unwrap();
    // Unsorted, with a repeat: the keyframed decode answers in the caller's order.
    let targets = [2.5, 0.0, 1.25, 3.0, 0.7, 1.25, 2.9];
    let plain = engine.decode(&encoding, &targets).unwrap();
    for keyframes in [
        Keyframes::Exact,
        Keyframes::adaptive(0.0, 64),
        Keyframes::Count { n: 7 },
    ] {
        let (sets, stats) = engine
            .decode_keyframed(&encoding, &targets, &keyframes)
            .unwrap();
        assert_eq!(bits(&sets), bits(&plain), "{keyframes:?}");
        assert_eq!(stats.exact_decodes, targets.len(), "{keyframes:?}");
        assert_eq!(stats.interpolated, 0);
        assert_eq!(stats.keyframe_times, [0.0, 0.7, 1.25, 2.5, 2.9, 3.0]);
    }
}

#[test]
fn uniform_keyframes_decode_only_the_keyframes_and_interpolate_the_rest() {
    if common::skip_reason().is_some() {
        return;
    }
    let engine = common::engine();
    let encoding = engine
        .encode(&common::synthetic_frames(&[0.0, 1.0, 2.0, 3.0]))
        .unwrap();
    let targets = even(&encoding, 13);
    let (sets, stats) = engine
        .decode_keyframed(&encoding, &targets, &Keyframes::Count { n: 4 })
        .unwrap();
    assert_eq!(stats.exact_decodes, 4);
    assert_eq!(stats.keyframe_times, [0.0, 1.0, 2.0, 3.0]);
    assert_eq!(stats.interpolated, 9);
    assert_eq!(sets.len(), 13);
    for set in &sets {
        set.validate().unwrap();
    }
    // Every fourth target is a keyframe: the exact decode of that time.
    let exact = engine.decode(&encoding, &[0.0, 1.0, 2.0, 3.0]).unwrap();
    for (k, set) in exact.iter().enumerate() {
        let d = deviation(set, &sets[4 * k]).unwrap();
        // One decoder run against another of a different batch: rounding only.
        assert!(d.position < 1e-5, "{d:?}");
    }
}

/// The adaptive mode on the trained model: at 40 random times inside the span (each a requested
/// time, none of them known to the refinement except as targets), the largest position error
/// against exact decodes stays within the tolerance, for fewer decodes than exact. Also prints
/// exact against count-8 and adaptive over 64 evenly spaced times (the numbers in
/// docs/benchmarks.md).
#[test]
fn adaptive_keyframes_stay_within_their_tolerance_on_c4g_tiny() {
    if common::skip_reason().is_some() {
        return;
    }
    let engine = tiny();
    let encoding = tiny_clip();
    let (lo, hi) = encoding.time_span();
    // A fixed-seed linear congruential generator: the same times every run.
    let mut state = 0x2545_f491_4f6c_dd1du64;
    let mut random = || {
        state = state
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        lo + (hi - lo) * ((state >> 11) as f64 / (1u64 << 53) as f64)
    };
    let checks: Vec<f64> = (0..40).map(|_| random()).collect();
    let exact = engine.decode(&encoding, &checks).unwrap();
    for tolerance in [0.02, 0.005, 0.001] {
        let keyframes = Keyframes::adaptive(tolerance, 64);
        let (sets, stats) = engine
            .decode_keyframed(&encoding, &checks, &keyframes)
            .unwrap();
        let error = worst(&sets, &exact);
        eprintln!(
            "random 40, tolerance {tolerance}: {} exact decodes, {} interpolated, {} rounds, error {error:?}",
            stats.exact_decodes, stats.interpolated, stats.rounds
        );
        assert!(
            error.position <= tolerance,
            "tolerance {tolerance}: position error {}",
            error.position
        );
        assert!(stats.exact_decodes < checks.len(), "{stats:?}");
    }

    let targets = even(&encoding, 64);
    let exact = engine.decode(&encoding, &targets).unwrap();
    for keyframes in [
        Keyframes::Count { n: 8 },
        Keyframes::Count { n: 16 },
        Keyframes::adaptive(0.01, 64),
        Keyframes::adaptive(0.005, 64),
        Keyframes::adaptive(0.001, 64),
    ] {
        let (sets, stats) = engine
            .decode_keyframed(&encoding, &targets, &keyframes)
            .unwrap();
        let error = worst(&sets, &exact);
        eprintln!(
            "even 64, {keyframes:?}: {} exact decodes in {} runs, {} interpolated, error {error:?}",
            stats.exact_decodes, stats.decoder_runs, stats.interpolated
        );
        if let Keyframes::Adaptive { tolerance, .. } = keyframes {
            assert!(error.position <= tolerance, "{keyframes:?}: {error:?}");
        }
    }
}
