//! Batching across requests (`service/src/sets/batching.rs`): concurrent exact decodes and renders of
//! one clip share decoder runs, and each request still gets what it would have got alone.
//!
//! The server runs on the CPU with a wait long enough (`C4G_BATCH_WAIT_MS=100`) for requests sent
//! together by threads to meet, and work slots for all of them. Checked: twelve concurrent
//! single-target requests (eight decodes, four renders) are answered by fewer decoder runs than
//! requests (`c4g_decode_duration_seconds_count`, one sample a decoder call); the batch metrics
//! add up; each decoded set agrees with the set decoded alone, and each render with the render
//! made alone.
//!
//! Closeness, not equality: ONNX Runtime's CPU kernels split a matrix product over threads by its
//! shape, so a target decoded among others may round differently from the same target alone
//! (seen here: equal bits in one run, not in another, as the batches formed differently). The sets
//! must agree within 1e-4 in every parameter (rounding of f32 sums is about 1e-6 here; a target
//! mixed up with another differs by far more), and renders within 2 of 255 per channel.

#![allow(clippy::unwrap_used, clippy::expect_used, missing_docs)]

use c4g_e2e::{Server, metric, ort_available, upload_synthetic};
use reqwest::blocking::Client;
use serde_json::json;

fn metrics(server: &Server) -> String {
    Client::new()
        .get(server.at("/metrics"))
        .send()
        .unwrap()
        .text()
        .unwrap()
}

fn decode(server: &Server, id: &str, t: f64) -> Vec<u8> {
    let response = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/gaussians")))
        .json(&json!({"t": t, "format": "binary"}))
        .send()
        .unwrap();
    assert_eq!(response.status(), 200);
    response.bytes().unwrap().to_vec()
}

fn render(server: &Server, id: &str, t: f64) -> Vec<u8> {
    let response = Client::new()
        .post(server.at(&format!("/v1/clips/{id}/render")))
        .json(&json!({"t": t, "width": 64, "height": 64}))
        .send()
        .unwrap();
    assert_eq!(response.status(), 200);
    response.bytes().unwrap().to_vec()
}

#[test]
fn concurrent_exact_requests_share_decoder_runs_and_get_what_they_would_alone() {
    if !ort_available() {
        return;
    }
    let server = Server::start_env(
        &[
            ("C4G_BATCH_WAIT_MS", "100"),
            ("C4G_MAX_CONCURRENT_WORK", "16"),
        ],
        &[],
    );
    let id = upload_synthetic(&server);
    let decode_times: Vec<f64> = (0..8).map(|k| 0.05 + 0.07 * f64::from(k)).collect();
    let render_times = [0.1, 0.25, 0.4, 0.55];

    let before = metric(&metrics(&server), "c4g_decode_duration_seconds_count");
    let (decoded, rendered) = std::thread::scope(|s| {
        let decodes: Vec<_> = decode_times
            .iter()
            .map(|&t| {
                let (server, id) = (&server, &id);
                s.spawn(move || decode(server, id, t))
            })
            .collect();
        let renders: Vec<_> = render_times
            .iter()
            .map(|&t| {
                let (server, id) = (&server, &id);
                s.spawn(move || render(server, id, t))
            })
            .collect();
        (
            decodes
                .into_iter()
                .map(|h| h.join().unwrap())
                .collect::<Vec<_>>(),
            renders
                .into_iter()
                .map(|h| h.join().unwrap())
                .collect::<Vec<_>>(),
        )
    });
    let text = metrics(&server);
    let runs = metric(&text, "c4g_decode_duration_seconds_count") - before;
    let requests = decode_times.len() + render_times.len();
    assert!(
        runs < requests as f64,
        "{requests} concurrent requests took {runs} decoder runs: nothing was batched"
    );
    assert_eq!(
        metric(&text, "c4g_decode_batch_requests_sum"),
        requests as f64
    );
    assert_eq!(
        metric(&text, "c4g_decode_batch_targets_sum"),
        requests as f64
    );
    assert_eq!(metric(&text, "c4g_decode_batch_requests_count"), runs);
    eprintln!("batching: {requests} concurrent single-target requests in {runs} decoder runs");

    // Alone, one after another: the same sets and renders, within rounding.
    for (t, batched) in decode_times.iter().zip(&decoded) {
        let (alone, batched) = (sets(&decode(&server, &id, *t)), sets(batched));
        let worst = alone
            .iter()
            .zip(&batched)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(
            alone.len() == batched.len() && worst <= 1e-4,
            "the set at t={t} decoded in a batch differs from the set decoded alone by {worst}"
        );
    }
    for (t, batched) in render_times.iter().zip(&rendered) {
        let alone = image::load_from_memory(&render(&server, &id, *t))
            .unwrap()
            .to_rgb8();
        let batched = image::load_from_memory(batched).unwrap().to_rgb8();
        let worst = alone
            .as_raw()
            .iter()
            .zip(batched.as_raw())
            .map(|(a, b)| a.abs_diff(*b))
            .max()
            .unwrap_or(0);
        assert!(
            worst <= 2,
            "the render at t={t} differs by {worst} of 255 when its decode was batched"
        );
    }
}

/// Every parameter of the sets in a C4GS answer, in order.
fn sets(bytes: &[u8]) -> Vec<f32> {
    c4g_formats::c4gs::decode(bytes)
        .unwrap()
        .into_iter()
        .flat_map(|(_, set)| set.to_canonical())
        .collect()
}

#[test]
fn without_a_wait_every_request_decodes_on_its_own() {
    if !ort_available() {
        return;
    }
    // The CPU default: no batching.
    let server = Server::start(&[]);
    let id = upload_synthetic(&server);
    let before = metric(&metrics(&server), "c4g_decode_duration_seconds_count");
    std::thread::scope(|s| {
        for k in 0..4 {
            let (server, id) = (&server, &id);
            s.spawn(move || decode(server, id, 0.1 * f64::from(k)));
        }
    });
    let text = metrics(&server);
    assert_eq!(
        metric(&text, "c4g_decode_duration_seconds_count") - before,
        4.0
    );
    assert_eq!(metric(&text, "c4g_decode_batch_requests_count"), 0.0);
}
