//! The compact 4D stream (`C4GV`) end to end: REST `POST /v1/clips/{id}/stream` and gRPC
//! `StreamGaussians` with `compact`, against the exact sets REST decodes at the same times.
//!
//! Reference: `POST /v1/clips/{id}/gaussians` in the binary format at f32 (bit-exact sets).
//! Tolerances are the codec's stated bounds (`formats/src/c4gv/mod.rs`): positions within
//! the asked `position_error` per coordinate, scales within 4.9e-4 relative, rotations within
//! 4.9e-4 rad, opacity and colour within 4.9e-4; each bound with 1e-6 of slack for the f32
//! rounding of the values compared (the bounds are stated in f64 of the decoded f32s).
#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{Server, ort_available, post_json, upload_synthetic};
use c4g_formats::{c4gs, c4gv};
use c4g_proto::v1 as pb;
use c4g_proto::v1::c4g_client::C4gClient;
use c4g_scene::GaussianSet;
use serde_json::{Value, json};

const SLACK: f64 = 1e-6;

fn post(server: &Server, path: &str, body: Value) -> reqwest::blocking::Response {
    post_json(server, path, &body)
}

/// The exact sets at `times`, and their C4GS f32 size.
fn exact(
    server: &Server,
    id: &str,
    times: &[f64],
    quality: &str,
) -> (Vec<(f64, GaussianSet)>, usize) {
    let response = post(
        server,
        &format!("/v1/clips/{id}/gaussians"),
        json!({"times": times, "format": "binary", "quality": quality}),
    );
    assert_eq!(response.status(), 200);
    let bytes = response.bytes().unwrap();
    (c4gs::decode(&bytes).unwrap(), bytes.len())
}

/// Asserts every bound of `position_error` between `got` and `want`.
fn within_bounds(got: &[(f64, GaussianSet)], want: &[(f64, GaussianSet)], position_error: f64) {
    assert_eq!(got.len(), want.len());
    for ((tg, g), (tw, w)) in got.iter().zip(want) {
        assert_eq!(tg, tw);
        assert_eq!(g.len(), w.len());
        for i in 0..g.len() {
            let (a, b) = (g.get(i).unwrap(), w.get(i).unwrap());
            let worst = (a.position - b.position).abs().max_element();
            assert!(
                f64::from(worst) <= position_error + SLACK,
                "position off by {worst} at {tg} s"
            );
            for (x, y) in a.scale.to_array().into_iter().zip(b.scale.to_array()) {
                let relative = c4gv::scale_error(y, x);
                assert!(relative <= c4gv::SCALE_ERROR + SLACK, "scale {y} -> {x}");
            }
            let angle = c4gv::rotation_angle(g.rotations()[i], w.rotations()[i]);
            assert!(
                angle <= c4gv::ROTATION_ERROR + SLACK,
                "rotation off by {angle} rad"
            );
            assert!(f64::from((a.opacity - b.opacity).abs()) <= c4gv::OPACITY_ERROR + SLACK);
            let colour = (a.color - b.color).abs().max_element();
            assert!(f64::from(colour) <= c4gv::COLOR_ERROR + SLACK);
        }
    }
}

#[test]
fn the_rest_stream_is_the_exact_sets_within_its_bound_in_a_fraction_of_the_bytes() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    for (position_error, quality) in [(1e-3, "exact"), (1e-4, "exact"), (1e-3, "fast")] {
        let response = post(
            &server,
            &format!("/v1/clips/{id}/stream"),
            json!({"step": 0.02, "position_error": position_error, "quality": quality}),
        );
        assert_eq!(response.status(), 200);
        assert_eq!(
            response.headers()["content-type"],
            "application/x-c4g-stream"
        );
        let sets: usize = response.headers()["x-c4g-sets"]
            .to_str()
            .unwrap()
            .parse()
            .unwrap();
        let stream = response.bytes().unwrap();
        let got = c4gv::decode(&stream).unwrap();
        assert_eq!(got.len(), sets);
        // The index record ends it, and names every frame.
        assert_eq!(c4gv::read_index(&stream).unwrap().len(), sets);
        let times: Vec<f64> = got.iter().map(|(t, _)| *t).collect();
        let (want, naive) = exact(&server, &id, &times, quality);
        within_bounds(&got, &want, position_error);
        // The acceptance bound: at most a quarter of naive f32 (measured: about 7%).
        assert!(
            stream.len() * 4 <= naive,
            "{} bytes against {naive} for C4GS f32 at {position_error}",
            stream.len()
        );
    }
}

#[test]
fn a_rate_too_low_for_the_span_streams_one_set_at_the_start() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    for body in [json!({"fps": 5e-324}), json!({"step": 1e6, "start": 0.1})] {
        let response = post(&server, &format!("/v1/clips/{id}/stream"), body.clone());
        assert_eq!(response.status(), 200, "{body}");
        let frames = c4gv::decode(&response.bytes().unwrap()).unwrap();
        assert_eq!(frames.len(), 1, "{body}");
        assert_eq!(frames[0].0, body["start"].as_f64().unwrap_or(0.0));
    }
}

#[test]
fn bad_stream_options_are_refused_with_what_to_change() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    for (body, says) in [
        (
            json!({"position_error": 0}),
            "position_error must be between",
        ),
        (
            json!({"position_error": 2}),
            "position_error must be between",
        ),
        (
            json!({"keyframe_interval": 0}),
            "keyframe_interval must be between",
        ),
        (json!({"step": 0.1, "fps": 10}), "not both"),
        (json!({"step": 1e-9}), "C4G_MAX_TIMES"),
        (json!({"colour": true}), "unknown field"),
    ] {
        let response = post(&server, &format!("/v1/clips/{id}/stream"), body.clone());
        assert!(response.status().is_client_error(), "{body}");
        let error: Value = serde_json::from_str(&response.text().unwrap()).unwrap();
        let error = error["error"].as_str().unwrap().to_owned();
        assert!(error.contains(says), "{body}: {error}");
    }
}

#[test]
fn the_grpc_compact_stream_is_the_rest_stream_piece_by_piece() {
    if !ort_available() {
        return;
    }
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    let rest = post(
        &server,
        &format!("/v1/clips/{id}/stream"),
        json!({"step": 0.05, "keyframe_interval": 4}),
    )
    .bytes()
    .unwrap();
    let runtime = tokio::runtime::Runtime::new().unwrap();
    let pieces: Vec<pb::GaussianFrame> = runtime.block_on(async {
        let mut grpc = C4gClient::connect(server.url()).await.unwrap();
        let mut stream = grpc
            .stream_gaussians(pb::StreamGaussiansRequest {
                clip_id: id.clone(),
                spacing: Some(pb::stream_gaussians_request::Spacing::Step(0.05)),
                compact: Some(pb::CompactStream {
                    position_error: 0.0,
                    keyframe_interval: 4,
                }),
                ..Default::default()
            })
            .await
            .unwrap()
            .into_inner();
        let mut pieces = Vec::new();
        while let Some(piece) = stream.message().await.unwrap() {
            pieces.push(piece);
        }
        pieces
    });
    // One piece per set, then the index; no GaussianSet messages.
    let sets = c4gv::decode(&rest).unwrap().len();
    assert_eq!(pieces.len(), sets + 1);
    assert!(pieces.iter().all(|p| p.gaussians.is_none()));
    let joined: Vec<u8> = pieces.iter().flat_map(|p| p.c4gv.clone()).collect();
    // The same sets quantised the same way: the same bytes.
    assert_eq!(joined, rest.to_vec());
    // A reader fed piece by piece has each set as soon as its piece arrives.
    let mut decoder = c4gv::Decoder::new();
    for (k, piece) in pieces.iter().take(sets).enumerate() {
        decoder.feed(&piece.c4gv);
        let (time, _) = decoder.next_frame().unwrap().expect("a set per piece");
        assert_eq!(time, piece.time, "piece {k}");
    }
}
