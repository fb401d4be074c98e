//! Captions to prompt embeddings against diffusers' WanVACEPipeline.encode_prompt on the tiny
//! fixture (`reference/text.json`, `text.npz`, made by `c4g.wan.export --tiny` with ftfy
//! installed, as the pipeline needs):
//! - the clean-up equals `prompt_clean` on the reference captions and on 300 random strings of
//!   entities, markup, whitespace, controls and typography, exactly;
//! - token ids and masks equal the transformers tokenizer's, exactly;
//! - embeddings match within 1e-5 absolute (measured 7e-7: ONNX Runtime against PyTorch, f32),
//!   and are zero after the real tokens;
//! - the default negative prompt (empty) is the embedding of "".
#![allow(clippy::unwrap_used, clippy::expect_used)]

mod common;

use std::sync::OnceLock;

use c4g_refiner::text::clean_caption;
use c4g_refiner::{Pipeline, PipelineOptions};
use common::*;
use serde_json::Value;

const ATOL: f32 = 1e-5;

fn reference() -> Value {
    let path = reference_dir().join("text.json");
    serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap()
}

fn pipeline() -> &'static Pipeline {
    static P: OnceLock<Pipeline> = OnceLock::new();
    P.get_or_init(|| Pipeline::load(fixture_dir(), &PipelineOptions::default()).unwrap())
}

fn ids(value: &Value) -> Vec<i64> {
    value
        .as_array()
        .unwrap()
        .iter()
        .map(|v| v.as_i64().unwrap())
        .collect()
}

#[test]
fn captions_are_cleaned_as_the_pipeline_cleans_them() {
    if fixture_skip_reason().is_some() {
        return;
    }
    let reference = reference();
    let mut pairs: Vec<(String, String)> = reference["cases"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            (
                c["caption"].as_str().unwrap().to_owned(),
                c["clean"].as_str().unwrap().to_owned(),
            )
        })
        .collect();
    pairs.extend(
        reference["clean_cases"]
            .as_array()
            .unwrap()
            .iter()
            .map(|c| {
                (
                    c[0].as_str().unwrap().to_owned(),
                    c[1].as_str().unwrap().to_owned(),
                )
            }),
    );
    assert!(pairs.len() > 300);
    let wrong: Vec<_> = pairs
        .iter()
        .filter(|(caption, clean)| clean_caption(caption) != *clean)
        .map(|(caption, clean)| {
            format!(
                "{caption:?}: {:?}, expected {clean:?}",
                clean_caption(caption)
            )
        })
        .collect();
    assert!(
        wrong.is_empty(),
        "{} of {} differ:\n{}",
        wrong.len(),
        pairs.len(),
        wrong.join("\n")
    );
}

#[test]
fn tokens_and_embeddings_match_the_pipeline() {
    if skip_reason().is_some() {
        return;
    }
    let reference = reference();
    let encoder = pipeline()
        .text_encoder()
        .expect("the fixture has a text encoder");
    let m = pipeline().manifest();
    let (tokens, dim) = (m.text.tokens, m.text.dim);
    let mut npz = Npz::open("text.npz");
    let expected = npz.vec("embeddings");
    let cases = reference["cases"].as_array().unwrap();
    assert_eq!(expected.len(), cases.len() * tokens * dim);
    for (case, expected) in cases.iter().zip(expected.chunks(tokens * dim)) {
        let caption = case["caption"].as_str().unwrap();
        let t = encoder.tokenize(caption).unwrap();
        assert_eq!(t.ids, ids(&case["input_ids"]), "ids of {caption:?}");
        assert_eq!(t.mask, ids(&case["attention_mask"]), "mask of {caption:?}");
        let embedding = pipeline().embed_caption(caption).unwrap();
        assert_close(&embedding, expected, ATOL, 0.0, caption);
        assert!(embedding[t.len * dim..].iter().all(|&v| v == 0.0));
        assert!(embedding[..t.len * dim].iter().any(|&v| v != 0.0));
    }
    let negative = npz.vec("negative_default");
    let empty = pipeline().embed_caption("").unwrap();
    assert_close(&empty, &negative, ATOL, 0.0, "the empty negative prompt");
}

#[test]
fn a_package_loaded_without_its_text_encoder_says_how_to_prompt() {
    if skip_reason().is_some() {
        return;
    }
    let options = PipelineOptions {
        skip_text_encoder: true,
        ..PipelineOptions::default()
    };
    let p = Pipeline::load(fixture_dir(), &options).unwrap();
    assert!(p.text_encoder().is_none());
    let err = p.embed_caption("a cube").unwrap_err();
    assert!(
        err.to_string().contains("precomputed text embedding"),
        "{err}"
    );
}
