//! The two decoder forms (`decoder_form` in docs/package.md) through the engine, on the fixture
//! `models/fixtures/decoder-forms`: one small seeded random model exported as `plain/` and as
//! `precomputed/` (its context projection computed once per encoding), with the PyTorch mirror's
//! outputs (`python -m c4g.package.fixture --decoder-forms`).
//!
//! Both forms decode the mirror's Gaussians and lifted features within 1e-4 (the parity tolerance;
//! the forms differ by float rounding only, about 1e-6), and each other's within the same bound.
//! The precomputed form's projection is made by `encode`, or on the first decode of an encoding
//! rebuilt from its parts, and an encoding from either engine decodes on the other.
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::path::{Path, PathBuf};

use c4g_engine::package::DecoderForm;
use c4g_engine::{
    ContextFrame, Encoding, Engine, EngineError, EngineOptions, ErrorKind, TimePolicy,
};
use c4g_scene::GaussianSet;
use common::{max_abs_diff, skip_reason, workspace};
use safetensors::SafeTensors;
use serde_json::Value;

const TOL: f32 = 1e-4;

fn forms_dir() -> PathBuf {
    workspace().join("models/fixtures/decoder-forms")
}

fn engine(form: &str, max_batch: usize) -> Engine {
    let options = EngineOptions {
        time_policy: Some(TimePolicy::Stable),
        max_batch,
        ..EngineOptions::default()
    };
    Engine::load(forms_dir().join(form), options).unwrap()
}

fn f32_tensor(st: &SafeTensors, name: &str) -> Vec<f32> {
    let view = st.tensor(name).unwrap_or_else(|e| panic!("{name}: {e}"));
    view.data()
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

fn numbers(v: &Value) -> Vec<f64> {
    v.as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_f64().unwrap())
        .collect()
}

/// One reference case: its context frames, targets and the mirror's outputs.
struct Case {
    name: String,
    frames: Vec<ContextFrame>,
    targets: Vec<f64>,
    features: Vec<f32>,
    gaussians: Vec<f32>,
    gaussian_features: Vec<f32>,
    feature_maps: Vec<f32>,
}

fn cases() -> Vec<Case> {
    let dir = forms_dir();
    let bytes = std::fs::read(dir.join("reference.safetensors")).unwrap();
    let st = SafeTensors::deserialize(&bytes).unwrap();
    let meta: Value =
        serde_json::from_slice(&std::fs::read(dir.join("reference.json")).unwrap()).unwrap();
    let frames = f32_tensor(&st, "frames");
    let maps = f32_tensor(&st, "feature_maps");
    let frame_len = frames.len() / st.tensor("frames").unwrap().shape()[0];
    let map_len = maps.len() / st.tensor("feature_maps").unwrap().shape()[0];
    meta["cases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|case| {
            assert_eq!(case["policy"], "stable");
            let name = case["case"].as_str().unwrap().to_owned();
            let times = numbers(&case["times"]);
            let t = times.len();
            Case {
                frames: times
                    .iter()
                    .enumerate()
                    .map(|(i, &time)| {
                        ContextFrame::new(time, frames[i * frame_len..(i + 1) * frame_len].to_vec())
                    })
                    .collect(),
                targets: numbers(&case["targets"]),
                features: f32_tensor(&st, &format!("{name}/features")),
                gaussians: f32_tensor(&st, &format!("{name}/gaussians")),
                gaussian_features: f32_tensor(&st, &format!("{name}/gaussian_features")),
                feature_maps: maps[..t * map_len].to_vec(),
                name,
            }
        })
        .collect()
}

fn canonical(sets: &[GaussianSet]) -> Vec<f32> {
    sets.iter().flat_map(GaussianSet::to_canonical).collect()
}

fn lifted(sets: &[GaussianSet]) -> Vec<f32> {
    sets.iter()
        .flat_map(|s| s.features().unwrap().values().to_vec())
        .collect()
}

fn skip() -> bool {
    if skip_reason().is_some() {
        return true;
    }
    assert!(
        forms_dir().join("reference.json").is_file(),
        "the decoder-forms fixture is missing: python -m c4g.package.fixture --decoder-forms"
    );
    false
}

#[test]
fn the_fixture_holds_one_package_of_each_form() {
    if skip() {
        return;
    }
    let plain = engine("plain", 16);
    let precomputed = engine("precomputed", 16);
    assert_eq!(plain.manifest().decoder_form, DecoderForm::Plain);
    assert_eq!(
        precomputed.manifest().decoder_form,
        DecoderForm::Precomputed
    );
    assert!(plain.package().context_projection_path().is_none());
    assert!(precomputed.package().context_projection_path().is_some());
}

#[test]
fn both_forms_decode_the_mirrors_gaussians_and_features_and_each_others() {
    if skip() {
        return;
    }
    let plain = engine("plain", 16);
    // Batches of two: the projection feeds every chunk of a decode.
    let precomputed = engine("precomputed", 2);
    for case in cases() {
        let name = &case.name;
        let mut decoded = Vec::new();
        for (form, engine) in [("plain", &plain), ("precomputed", &precomputed)] {
            let encoding = engine.encode(&case.frames).unwrap();
            let err = max_abs_diff(encoding.features(), &case.features);
            assert!(err <= TOL, "{name} {form}: features differ by {err:e}");
            let sets = engine.decode(&encoding, &case.targets).unwrap();
            let err = max_abs_diff(&canonical(&sets), &case.gaussians);
            assert!(err <= TOL, "{name} {form}: Gaussians differ by {err:e}");
            let with_features = engine
                .decode_features(&encoding, &case.feature_maps, &case.targets)
                .unwrap();
            let err = max_abs_diff(&lifted(&with_features), &case.gaussian_features);
            assert!(
                err <= TOL,
                "{name} {form}: lifted features differ by {err:e}"
            );
            decoded.push(canonical(&sets));
        }
        let err = max_abs_diff(&decoded[0], &decoded[1]);
        assert!(err <= TOL, "{name}: the forms differ by {err:e}");
    }
}

#[test]
fn encode_keeps_the_context_projection_and_a_rebuilt_encoding_makes_it_on_its_first_decode() {
    if skip() {
        return;
    }
    let precomputed = engine("precomputed", 16);
    let case = cases().pop().unwrap();
    let encoding = precomputed.encode(&case.frames).unwrap();
    let [t, p, c] = encoding.shape();
    let projection = encoding.context_projection().unwrap();
    assert_eq!(projection.len(), t * p * 3 * c);
    let bare = encoding.features().len() * 4;
    assert!(encoding.memory_bytes() >= bare + projection.len() * 4);
    let expected = canonical(&precomputed.decode(&encoding, &case.targets).unwrap());

    let (times, order, features, shape) = encoding.clone().into_parts();
    let rebuilt = Encoding::from_parts(times, order, features, shape).unwrap();
    assert_eq!(rebuilt.context_projection(), None);
    assert!(rebuilt.memory_bytes() < bare + projection.len() * 4);
    let sets = precomputed.decode(&rebuilt, &case.targets).unwrap();
    assert_eq!(rebuilt.context_projection(), Some(projection));
    assert_eq!(rebuilt, encoding);
    assert!(max_abs_diff(&canonical(&sets), &expected) <= 1e-6);
}

#[test]
fn an_encoding_from_either_engine_decodes_on_the_other() {
    if skip() {
        return;
    }
    let plain = engine("plain", 16);
    let precomputed = engine("precomputed", 16);
    let case = cases().pop().unwrap();
    let from_plain = plain.encode(&case.frames).unwrap();
    assert_eq!(from_plain.context_projection(), None);
    let from_precomputed = precomputed.encode(&case.frames).unwrap();
    let on_precomputed = canonical(&precomputed.decode(&from_plain, &case.targets).unwrap());
    let on_plain = canonical(&plain.decode(&from_precomputed, &case.targets).unwrap());
    assert!(max_abs_diff(&on_precomputed, &case.gaussians) <= TOL);
    assert!(max_abs_diff(&on_plain, &case.gaussians) <= TOL);
    // Another engine of the same package makes its own projection rather than trust this one's.
    let again = engine("precomputed", 16);
    let on_again = canonical(&again.decode(&from_precomputed, &case.targets).unwrap());
    assert!(max_abs_diff(&on_again, &case.gaussians) <= TOL);
}

/// A copy of the fixture package `form` in a temporary directory, its manifest edited by `edit`.
fn edited_copy(form: &str, edit: impl FnOnce(&mut Value, &Path)) -> tempfile::TempDir {
    let tmp = tempfile::tempdir().unwrap();
    for entry in std::fs::read_dir(forms_dir().join(form)).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), tmp.path().join(entry.file_name())).unwrap();
    }
    let path = tmp.path().join("model.json");
    let mut manifest: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    edit(&mut manifest, tmp.path());
    std::fs::write(&path, manifest.to_string()).unwrap();
    tmp
}

fn load_error(dir: &Path) -> String {
    match Engine::load(dir, EngineOptions::default()) {
        Err(e @ EngineError::InvalidPackage { .. }) => {
            assert_eq!(e.kind(), ErrorKind::Package);
            e.to_string()
        }
        Err(other) => panic!("expected an invalid package, got {other}"),
        Ok(_) => panic!("expected an invalid package, it loaded"),
    }
}

#[test]
fn a_manifest_that_misstates_the_decoder_form_is_refused_at_load() {
    if skip() {
        return;
    }
    // A plain decoder declared precomputed: it lacks the context projection input.
    let plain = edited_copy("plain", |m, dir| {
        m["decoder_form"] = "precomputed".into();
        m["files"]["context_projection"] = "context_projection.onnx".into();
        std::fs::copy(
            forms_dir().join("precomputed/context_projection.onnx"),
            dir.join("context_projection.onnx"),
        )
        .unwrap();
    });
    let reason = load_error(plain.path());
    assert!(reason.contains("context_projection"), "{reason}");
    // A precomputed decoder declared plain: it has an input the plain contract does not know.
    let precomputed = edited_copy("precomputed", |m, _| {
        m["decoder_form"] = "plain".into();
        m["files"]
            .as_object_mut()
            .unwrap()
            .remove("context_projection");
    });
    let reason = load_error(precomputed.path());
    assert!(reason.contains("context_projection"), "{reason}");
}
