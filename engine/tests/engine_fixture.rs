//! The engine end to end on the fixture package (models/fixtures/c4g-small): real ONNX Runtime
//! sessions on the real exported graphs, checked for behaviour (shapes, validity, order and batch
//! independence, errors). Numerical parity with the PyTorch mirror lives in its own test.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use c4g_engine::{
    ContextFrame, Encoding, Engine, EngineError, EngineOptions, ErrorKind, TimePolicy,
};
use c4g_scene::GaussianSet;
use common::*;

const TIMES: [f64; 4] = [0.0, 2.0, 4.0, 6.0];

fn encode_default() -> Encoding {
    engine().encode(&synthetic_frames(&TIMES)).unwrap()
}

fn canonical(sets: &[GaussianSet]) -> Vec<f32> {
    sets.iter().flat_map(GaussianSet::to_canonical).collect()
}

fn lifted(sets: &[GaussianSet]) -> Vec<f32> {
    sets.iter()
        .flat_map(|s| s.features().unwrap().values().to_vec())
        .collect()
}

/// Seeded noise feature maps, `[T, 256, 32]`, frame `i` distinct from frame `j`.
fn feature_maps(frames: usize) -> Vec<f32> {
    (0..frames * 256 * 32)
        .map(|i| ((i as f32) * 0.618_034).fract() * 2.0 - 1.0)
        .collect()
}

#[test]
fn the_fixture_loads_with_all_three_graphs() {
    if skip_reason().is_some() {
        return;
    }
    let engine = engine();
    assert!(engine.has_feature_decoder());
    let m = engine.manifest();
    assert_eq!(m.name, "c4g-small");
    assert_eq!(
        (m.tokens_per_frame, m.feature_width, m.gaussian_count),
        (256, 128, 256)
    );
    assert_eq!(m.feature_decoder_width(), Some(32));
}

#[test]
fn encode_gives_one_feature_vector_per_patch_of_each_frame() {
    if skip_reason().is_some() {
        return;
    }
    let encoding = encode_default();
    assert_eq!(encoding.shape(), [4, 256, 128]);
    assert_eq!(encoding.times(), &TIMES);
    assert_eq!(encoding.frame_order(), &[0, 1, 2, 3]);
    assert!(encoding.features().iter().all(|v| v.is_finite()));
}

#[test]
fn decode_gives_one_valid_gaussian_set_per_target() {
    if skip_reason().is_some() {
        return;
    }
    let encoding = encode_default();
    let sets = engine().decode(&encoding, &[0.0, 1.0, 3.0, 6.0]).unwrap();
    assert_eq!(sets.len(), 4);
    for set in &sets {
        assert_eq!(set.len(), 256);
        set.validate().unwrap();
        assert!(set.features().is_none());
    }
    // Time conditions the decoder: different moments give different Gaussians.
    assert!(max_abs_diff(&sets[0].to_canonical(), &sets[3].to_canonical()) > 1e-4);
    assert!(engine().decode(&encoding, &[]).unwrap().is_empty());
}

#[test]
fn encoding_does_not_depend_on_the_order_of_the_frames() {
    if skip_reason().is_some() {
        return;
    }
    let frames = synthetic_frames(&TIMES);
    let shuffled: Vec<ContextFrame> = [2, 0, 3, 1].iter().map(|&i| frames[i].clone()).collect();
    let a = engine().encode(&frames).unwrap();
    let b = engine().encode(&shuffled).unwrap();
    assert_eq!(b.times(), &TIMES);
    assert_eq!(b.features(), a.features());
    // Encoded frame k came from position frame_order[k] of the shuffled list.
    assert_eq!(b.frame_order(), &[1, 3, 0, 2]);
}

#[test]
fn frames_sharing_a_time_are_ordered_by_content() {
    if skip_reason().is_some() {
        return;
    }
    let frames = vec![
        ContextFrame::new(1.0, synthetic_pixels(7)),
        ContextFrame::new(1.0, synthetic_pixels(8)),
        ContextFrame::new(0.0, synthetic_pixels(9)),
    ];
    let reversed: Vec<ContextFrame> = frames.iter().rev().cloned().collect();
    let a = engine().encode(&frames).unwrap();
    let b = engine().encode(&reversed).unwrap();
    assert_eq!(a.features(), b.features());
    assert_eq!(a.times(), &[0.0, 1.0, 1.0]);
}

#[test]
fn batch_size_does_not_change_the_result() {
    if skip_reason().is_some() {
        return;
    }
    let one_at_a_time = Engine::load(
        fixture_dir(),
        EngineOptions {
            max_batch: 1,
            ..EngineOptions::default()
        },
    )
    .unwrap();
    let encoding = encode_default();
    let targets = [0.0, 0.5, 2.5, 5.0, 6.0];
    assert_eq!(engine().decode_batch_size(encoding.frame_count()), 16);
    let batched = engine().decode(&encoding, &targets).unwrap();
    let single = one_at_a_time.decode(&encoding, &targets).unwrap();
    let diff = max_abs_diff(&canonical(&batched), &canonical(&single));
    assert!(diff <= 1e-5, "batched and single decodes differ by {diff}");
}

#[test]
fn batches_shrink_to_fit_the_decoder_memory_budget() {
    if skip_reason().is_some() {
        return;
    }
    // Fixture decoder (fused attention, width 128): at T = 16 one target needs about
    // 8 · 128 · (16 · 256 + 256) · 4 B = 17.8 MB.
    let engine = engine();
    assert_eq!(engine.decode_batch_size(16), 16);
    let tight = Engine::load(
        fixture_dir(),
        EngineOptions {
            decoder_memory_budget: 50_000_000,
            ..EngineOptions::default()
        },
    )
    .unwrap();
    assert_eq!(tight.decode_batch_size(16), 2); // 50 MB / 17.8 MB = 2.8
    assert_eq!(tight.decode_batch_size(1), 16); // 512 tokens: 2.1 MB a target
    let unlimited = Engine::load(
        fixture_dir(),
        EngineOptions {
            decoder_memory_budget: 0,
            max_batch: 5,
            ..EngineOptions::default()
        },
    )
    .unwrap();
    assert_eq!(unlimited.decode_batch_size(16), 5);
}

#[test]
fn stable_and_reference_policies_agree_past_the_first_gap_and_differ_inside_it() {
    if skip_reason().is_some() {
        return;
    }
    let encoding = encode_default();
    let late = [3.0, 6.0];
    let reference = TimePolicy::Reference
        .normalize_all(encoding.times(), &late)
        .unwrap();
    let stable = stable_engine().decode(&encoding, &late).unwrap();
    let exact = engine().decode_normalized(&encoding, &reference).unwrap();
    assert_eq!(canonical(&stable), canonical(&exact));

    let early = TimePolicy::Reference
        .normalize_all(encoding.times(), &[1.0])
        .unwrap();
    let reference_early = engine().decode_normalized(&encoding, &early).unwrap();
    let stable_early = stable_engine().decode(&encoding, &[1.0]).unwrap();
    assert!(max_abs_diff(&canonical(&reference_early), &canonical(&stable_early)) > 1e-4);
}

#[test]
fn a_package_that_declares_no_policy_decodes_with_frame_step_and_options_override_it() {
    if skip_reason().is_some() {
        return;
    }
    assert_eq!(engine().manifest().time_policy, None);
    assert_eq!(engine().time_policy(), TimePolicy::FrameStep);
    assert_eq!(stable_engine().time_policy(), TimePolicy::Stable);
    // Inside stable's first interval, with the source's frame step known (30 fps), frame-step
    // is the reference: what the official weights were trained on.
    let encoding = encode_default().with_frame_step(Some(1.0 / 30.0)).unwrap();
    let targets = [1.0, 0.5, 3.0];
    let reference = TimePolicy::Reference
        .normalize_all(encoding.times(), &targets)
        .unwrap();
    let exact = engine().decode_normalized(&encoding, &reference).unwrap();
    let frame_step = engine().decode(&encoding, &targets).unwrap();
    assert_eq!(canonical(&frame_step), canonical(&exact));
    let stable = stable_engine().decode(&encoding, &targets[..1]).unwrap();
    assert!(max_abs_diff(&canonical(&stable), &canonical(&exact[..1])) > 1e-4);
    // Without a frame step, evenly spaced context frames: the fallback gap is the mean spacing.
    assert_eq!(
        canonical(&engine().decode(&encode_default(), &[0.0, 1.0]).unwrap()),
        canonical(
            &stable_engine()
                .decode(&encode_default(), &[0.0, 1.0])
                .unwrap()
        )
    );
}

#[test]
fn a_package_that_declares_stable_decodes_with_stable() {
    if skip_reason().is_some() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("c4g-declares-stable-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for f in ["encoder.onnx", "decoder.onnx", "feature_decoder.onnx"] {
        std::fs::copy(fixture_dir().join(f), dir.join(f)).unwrap();
    }
    let mut manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixture_dir().join("model.json")).unwrap())
            .unwrap();
    manifest["time_policy"] = "stable".into();
    std::fs::write(dir.join("model.json"), manifest.to_string()).unwrap();
    let declared = Engine::load(&dir, EngineOptions::default()).unwrap();
    let overridden = Engine::load(
        &dir,
        EngineOptions {
            time_policy: Some(TimePolicy::FrameStep),
            ..EngineOptions::default()
        },
    )
    .unwrap();
    std::fs::remove_dir_all(&dir).unwrap();
    assert_eq!(declared.time_policy(), TimePolicy::Stable);
    assert_eq!(overridden.time_policy(), TimePolicy::FrameStep);
    let encoding = encode_default().with_frame_step(Some(1.0 / 30.0)).unwrap();
    assert_eq!(
        declared.normalize(&encoding, &[1.0]).unwrap(),
        TimePolicy::Stable.normalize_all(&TIMES, &[1.0]).unwrap()
    );
}

#[test]
fn lifted_features_ride_on_the_gaussians() {
    if skip_reason().is_some() {
        return;
    }
    let encoding = encode_default();
    let sets = engine()
        .decode_features(&encoding, &feature_maps(4), &[0.0, 3.0])
        .unwrap();
    assert_eq!(sets.len(), 2);
    for set in &sets {
        let block = set.features().unwrap();
        assert_eq!((block.width(), block.len()), (32, 256));
        set.validate().unwrap();
    }
    // The Gaussians themselves are the plain decoder's.
    let plain = engine().decode(&encoding, &[0.0, 3.0]).unwrap();
    assert_eq!(canonical(&plain), canonical(&sets));
}

#[test]
fn feature_maps_follow_the_order_frames_were_given_in() {
    if skip_reason().is_some() {
        return;
    }
    let frames = synthetic_frames(&TIMES);
    let maps = feature_maps(4);
    let per_frame = 256 * 32;
    let order = [3, 1, 0, 2];
    let shuffled_frames: Vec<ContextFrame> = order.iter().map(|&i| frames[i].clone()).collect();
    let shuffled_maps: Vec<f32> = order
        .iter()
        .flat_map(|&i| maps[i * per_frame..(i + 1) * per_frame].to_vec())
        .collect();

    let a = engine().encode(&frames).unwrap();
    let b = engine().encode(&shuffled_frames).unwrap();
    let targets = [1.0, 5.0];
    let from_a = engine().decode_features(&a, &maps, &targets).unwrap();
    let from_b = engine()
        .decode_features(&b, &shuffled_maps, &targets)
        .unwrap();
    assert_eq!(lifted(&from_a), lifted(&from_b));

    // Handing the maps in the wrong order changes the result: the permutation matters.
    let wrong = engine().decode_features(&b, &maps, &targets).unwrap();
    assert!(max_abs_diff(&lifted(&from_a), &lifted(&wrong)) > 1e-4);
}

#[test]
fn a_package_without_a_feature_decoder_refuses_lifting() {
    if skip_reason().is_some() {
        return;
    }
    let dir = std::env::temp_dir().join(format!("c4g-no-lifting-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    for f in ["encoder.onnx", "decoder.onnx"] {
        std::fs::copy(fixture_dir().join(f), dir.join(f)).unwrap();
    }
    let mut manifest: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(fixture_dir().join("model.json")).unwrap())
            .unwrap();
    manifest["files"]["feature_decoder"] = serde_json::Value::Null;
    manifest["feature_decoder"] = serde_json::Value::Null;
    std::fs::write(dir.join("model.json"), manifest.to_string()).unwrap();

    let engine = Engine::load(&dir, EngineOptions::default()).unwrap();
    let encoding = engine.encode(&synthetic_frames(&[0.0])).unwrap();
    assert_eq!(engine.decode(&encoding, &[0.0]).unwrap().len(), 1);
    let err = engine
        .decode_features(&encoding, &feature_maps(1), &[0.0])
        .unwrap_err();
    std::fs::remove_dir_all(&dir).unwrap();
    assert!(matches!(err, EngineError::NoFeatureDecoder { .. }), "{err}");
    assert_eq!(err.kind(), ErrorKind::Unsupported);
}

#[test]
fn bad_requests_get_clear_errors() {
    if skip_reason().is_some() {
        return;
    }
    let engine = engine();
    let encoding = encode_default();

    let err = engine.decode(&encoding, &[7.0]).unwrap_err();
    assert!(
        matches!(err, EngineError::TargetOutsideContext { .. }),
        "{err}"
    );
    assert!(err.to_string().contains("cannot extrapolate"));

    let err = engine.encode(&[]).unwrap_err();
    assert!(matches!(err, EngineError::InvalidInput(_)), "{err}");

    let err = engine
        .encode(&[ContextFrame::new(0.0, vec![0.0; 10])])
        .unwrap_err();
    assert!(err.to_string().contains("[3, 224, 224]"), "{err}");

    let err = engine
        .encode(&[ContextFrame::new(f64::NAN, synthetic_pixels(0))])
        .unwrap_err();
    assert!(matches!(err, EngineError::NonFiniteTime { .. }), "{err}");

    let mut pixels = synthetic_pixels(0);
    pixels[5] = f32::INFINITY;
    let err = engine
        .encode(&[ContextFrame::new(0.0, pixels)])
        .unwrap_err();
    assert_eq!(err.kind(), ErrorKind::InvalidInput);

    let err = engine
        .decode_features(&encoding, &feature_maps(3), &[1.0])
        .unwrap_err();
    assert!(matches!(err, EngineError::Shape { .. }), "{err}");

    let foreign =
        Encoding::from_parts(vec![0.0], vec![0], vec![0.0; 256 * 64], [1, 256, 64]).unwrap();
    let err = engine.decode(&foreign, &[0.0]).unwrap_err();
    assert!(matches!(err, EngineError::Shape { .. }), "{err}");

    let mut rows = TimePolicy::Stable
        .normalize_all(encoding.times(), &[1.0])
        .unwrap();
    rows[0].context.pop();
    let err = engine.decode_normalized(&encoding, &rows).unwrap_err();
    assert!(matches!(err, EngineError::Shape { .. }), "{err}");
}

#[test]
fn one_engine_serves_several_threads() {
    if skip_reason().is_some() {
        return;
    }
    let encoding = encode_default();
    let expected = canonical(&engine().decode(&encoding, &[2.0, 4.0]).unwrap());
    std::thread::scope(|scope| {
        let workers: Vec<_> = (0..2)
            .map(|_| scope.spawn(|| canonical(&engine().decode(&encoding, &[2.0, 4.0]).unwrap())))
            .collect();
        for worker in workers {
            assert_eq!(worker.join().unwrap(), expected);
        }
    });
}

#[test]
fn real_frames_go_from_jpeg_to_gaussians() {
    if skip_reason().is_some() {
        return;
    }
    let frames_dir = shared_dir().join("data/bedroom/frames");
    if !frames_dir.is_dir() {
        eprintln!(
            "skipped: {} not found (set C4G_SHARED)",
            frames_dir.display()
        );
        return;
    }
    let engine = engine();
    let frames: Vec<ContextFrame> = [0, 4, 8]
        .iter()
        .map(|&i| {
            let bytes = std::fs::read(frames_dir.join(format!("{i:05}.jpg"))).unwrap();
            let rgb = c4g_engine::preprocess::decode_frame(&bytes).unwrap();
            ContextFrame::new(f64::from(i) / 30.0, engine.preprocess(&rgb).unwrap())
        })
        .collect();
    let encoding = engine.encode(&frames).unwrap();
    let (first, last) = encoding.time_span();
    let sets = engine
        .decode(&encoding, &[first, (first + last) / 2.0, last])
        .unwrap();
    assert_eq!(sets.len(), 3);
    for set in sets {
        assert_eq!(set.len(), 256);
        set.validate().unwrap();
    }
}
