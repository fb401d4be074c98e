//! Device-resident encodings (`EngineOptions::resident_budget`) on the CPU, where the "device" is
//! host memory: the bound decode runs the same graph on the same values through an I/O binding,
//! so it must give exactly the plain decode's Gaussians (no tolerance: the same kernels read the
//! same numbers; only how they reach the session differs), in both decoder forms (the precomputed
//! one binds the context projection too) and on a query subset; and the cache must keep what its
//! budget allows, least recently used first, placing an encoding again after a spill and never
//! one larger than the whole budget. On CUDA the same path binds device memory (`scripts/
//! device-check`); that is not run here.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_engine::{
    ContextFrame, Encoding, Engine, EngineOptions, QuerySubset, ResidentStats, TimePolicy,
};
use c4g_scene::GaussianSet;
use common::{skip_reason, workspace};

fn engine(package: &str, resident_budget: Option<usize>) -> Engine {
    let options = EngineOptions {
        time_policy: Some(TimePolicy::Stable),
        resident_budget,
        ..EngineOptions::default()
    };
    Engine::load(workspace().join(package), options).unwrap()
}

/// Deterministic frames of the package's input size, different for each `seed`.
fn encode(engine: &Engine, seed: u32) -> Encoding {
    let input = &engine.manifest().input;
    let (w, h) = (input.width as usize, input.height as usize);
    let frames: Vec<ContextFrame> = (0..4u32)
        .map(|f| {
            let pixels = (0..3 * w * h)
                .map(|i| {
                    let v = (i as u32).wrapping_mul(2_654_435_761) ^ (seed * 97 + f * 13);
                    (v % 2001) as f32 / 1000.0 - 1.0
                })
                .collect();
            ContextFrame::new(f64::from(f) * 0.2, pixels)
        })
        .collect();
    engine.encode(&frames).unwrap()
}

fn canonical(sets: &[GaussianSet]) -> Vec<f32> {
    sets.iter().flat_map(GaussianSet::to_canonical).collect()
}

const TARGETS: [f64; 3] = [0.1, 0.3, 0.55];

#[test]
fn a_resident_decode_is_the_plain_decode_in_both_forms() {
    if skip_reason().is_some() {
        return;
    }
    for package in [
        "models/fixtures/decoder-forms/plain",
        "models/fixtures/decoder-forms/precomputed",
    ] {
        let plain = engine(package, Some(0));
        let bound = engine(package, Some(64 << 20));
        assert_eq!(plain.resident_stats(), None, "0 turns residency off");
        let encoding = encode(&plain, 1);
        let expected = canonical(&plain.decode(&encoding, &TARGETS).unwrap());
        for round in 0..2 {
            let got = canonical(&bound.decode(&encoding, &TARGETS).unwrap());
            assert_eq!(got, expected, "{package}, round {round}");
        }
        let stats = bound.resident_stats().unwrap();
        assert_eq!(
            (stats.encodings, stats.placements, stats.hits),
            (1, 1, 1),
            "{package}"
        );
        let projection =
            bound.manifest().decoder_form == c4g_engine::package::DecoderForm::Precomputed;
        let per_value = if projection { 4 } else { 1 };
        assert_eq!(
            stats.bytes,
            4 * per_value * encoding.features().len(),
            "{package}"
        );
    }
}

#[test]
fn a_resident_decode_of_a_query_subset_is_the_plain_one() {
    if skip_reason().is_some() {
        return;
    }
    let plain = engine("models/c4g-tiny", None);
    let bound = engine("models/c4g-tiny", Some(64 << 20));
    assert_eq!(plain.resident_stats(), None, "off on the CPU by default");
    let encoding = encode(&plain, 2);
    let subset = QuerySubset::new(&[0, 5, 17, 200, 511], 512).unwrap();
    let expected = canonical(&plain.decode_subset(&encoding, &TARGETS, &subset).unwrap());
    let got = canonical(&bound.decode_subset(&encoding, &TARGETS, &subset).unwrap());
    assert_eq!(got, expected);
}

#[test]
fn the_cache_keeps_its_budget_spills_the_least_recent_and_places_again() {
    if skip_reason().is_some() {
        return;
    }
    let probe = engine("models/c4g-tiny", Some(0));
    let [a, b, c] = [1, 2, 3].map(|seed| encode(&probe, seed));
    let one = 4 * a.features().len();
    // Room for two encodings, not three.
    let bound = engine("models/c4g-tiny", Some(2 * one + one / 2));
    let decode = |e: &Encoding| bound.decode(e, &[0.3]).unwrap();
    decode(&a);
    decode(&b);
    decode(&a); // a is now the most recent
    decode(&c); // spills b
    let stats = bound.resident_stats().unwrap();
    assert_eq!(
        stats,
        ResidentStats {
            encodings: 2,
            bytes: 2 * one,
            placements: 3,
            hits: 1,
            spills: 1,
        }
    );
    decode(&a); // still there
    decode(&b); // placed again, spilling c
    let stats = bound.resident_stats().unwrap();
    assert_eq!((stats.placements, stats.hits, stats.spills), (4, 2, 2));
    // A clone is the same values: it finds the same copy.
    bound.decode(&a.clone(), &[0.3]).unwrap();
    assert_eq!(bound.resident_stats().unwrap().hits, 3);

    // An encoding larger than the whole budget decodes from host memory, never placed.
    let small = engine("models/c4g-tiny", Some(one / 2));
    let expected = canonical(&probe.decode(&a, &TARGETS).unwrap());
    assert_eq!(canonical(&small.decode(&a, &TARGETS).unwrap()), expected);
    assert_eq!(small.resident_stats().unwrap(), ResidentStats::default());
}
